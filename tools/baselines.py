"""Baselines a user would pick instead of EDI, for `tools/bench_accuracy.py` (pure numpy).

- `blurry(frame)`: the APS frame itself, as float linear intensity.
- `direct_integration(...)`: log L(t) = log B + c * (signed events between the frame's reference time and t),
  i.e. EDI without the deblurring step (Brandli et al. 2014 style, as davis-EDI-rs does between frames).
- `ComplementaryFilter`: Scheerlinck et al., ACCV 2018. Per event at a pixel
  logL <- beta*logL + (1-beta)*logF + c*p with beta = exp(-alpha*dt_pixel), alpha = 2*pi*cutoff_hz, and the
  same decay towards logF for every pixel at output time. Between two frames logF is constant, so the
  per-event recursion has the closed form
      logL(t) = logF + exp(-alpha (t - t0)) (logL(t0) - logF) + sum_k c_k exp(-alpha (t - t_k)),
  which this module evaluates with one weighted bincount per event batch (exactly equal to the per-event
  loop, no Python loop per event). Frames enter when their exposure ends (the filter is causal).

All images are float32 (height, width) linear intensity on the APS scale (0..255 for 8-bit frames).
"""

from __future__ import annotations

import math

import numpy as np

from edi_live.datatypes import Frame


def blurry(frame: Frame) -> np.ndarray:
    """The blurry APS frame itself (the 'do nothing' baseline)."""
    return frame.image.astype(np.float32)


def signed_log_increment(events: np.ndarray, width: int, height: int, c_on: float, c_off: float,
                         t_from_us: int, t_to_us: int) -> np.ndarray:
    """Per-pixel log-intensity change c_on*N_on - c_off*N_off from t_from_us to t_to_us.

    Counts events with t_from < t <= t_to; for t_to < t_from it is the negated change over (t_to, t_from]
    (going back in time undoes those events). float64 (height, width).
    """
    lo, hi, sign = (t_from_us, t_to_us, 1.0) if t_to_us >= t_from_us else (t_to_us, t_from_us, -1.0)
    t = events["t"]
    a, b = np.searchsorted(t, lo, side="right"), np.searchsorted(t, hi, side="right")
    ev = events[a:b]
    w = np.where(ev["p"], c_on, -c_off)
    flat = np.bincount(ev["y"].astype(np.int64) * width + ev["x"], weights=w, minlength=width * height)
    return sign * flat.reshape(height, width)


def direct_integration(frame: Frame, events: np.ndarray, t_us: int, c_on: float, c_off: float,
                       ref_us: int | None = None) -> np.ndarray:
    """B * exp(c * E(ref -> t)): the blurry frame taken as the image at ref (default mid-exposure).

    `events` must be time-ordered and cover [min(ref, t), max(ref, t)].
    """
    ref = frame.mid_exposure_us if ref_us is None else ref_us
    inc = signed_log_increment(events, frame.width, frame.height, c_on, c_off, ref, t_us)
    return (frame.image.astype(np.float64) * np.exp(inc)).astype(np.float32)


class ComplementaryFilter:
    """Scheerlinck 2018 complementary filter of events (high-pass) and APS frames (low-pass), in log space.

    Feed in time order: `add_events(batch)` with times after the last call, `add_frame(frame)` once the
    events up to its exposure end are in (the frame arrives at `exposure_end_us`), `image_at(t_us)` for
    t >= the last fed time. The state starts at the first frame's log image (the reference implementation
    starts at 0 and converges with time constant 1/alpha; starting at the frame is kinder to it).
    `eps` keeps log finite at B = 0 (linear scale offset, in DN).
    """

    def __init__(self, width: int, height: int, c_on: float, c_off: float, *, cutoff_hz: float = 0.5,
                 eps: float = 1.0) -> None:
        self.width, self.height = width, height
        self.c_on, self.c_off = float(c_on), float(c_off)
        self.alpha = 2.0 * math.pi * cutoff_hz
        self.eps = eps
        self._u: np.ndarray | None = None  # logL - logF at time self._t_us, flat float64
        self._log_f: np.ndarray | None = None
        self._t_us: int | None = None

    def _decay_to(self, t_us: int) -> None:
        if self._t_us is not None and t_us > self._t_us:
            self._u *= math.exp(-self.alpha * (t_us - self._t_us) * 1e-6)
            self._t_us = t_us

    def add_events(self, events: np.ndarray) -> None:
        if self._u is None or events.size == 0:
            return
        t_end = int(events["t"][-1])
        if t_end < self._t_us:
            raise ValueError("ComplementaryFilter: events must come in time order after the last update")
        self._decay_to(t_end)
        wts = np.where(events["p"], self.c_on, -self.c_off) * np.exp(
            -self.alpha * (t_end - events["t"]).astype(np.float64) * 1e-6)
        self._u += np.bincount(events["y"].astype(np.int64) * self.width + events["x"], weights=wts,
                               minlength=self.width * self.height)

    def add_frame(self, frame: Frame, t_us: int | None = None) -> None:
        t = frame.exposure_end_us if t_us is None else t_us
        log_new = np.log(frame.image.astype(np.float64).ravel() + self.eps)
        if self._u is None:
            self._u, self._t_us = np.zeros_like(log_new), t
        else:
            self._decay_to(t)
            self._u += self._log_f - log_new  # logL is continuous; only the low-pass target changes
        self._log_f = log_new

    def image_at(self, t_us: int) -> np.ndarray:
        """Linear image at t (>= the time of the last event/frame fed)."""
        if self._u is None:
            raise ValueError("ComplementaryFilter: no frame yet")
        k = math.exp(-self.alpha * max(t_us - self._t_us, 0) * 1e-6)
        img = np.exp(np.minimum(self._log_f + k * self._u, 30.0)) - self.eps  # hot pixels can run away
        return img.reshape(self.height, self.width).astype(np.float32)
