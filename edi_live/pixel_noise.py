"""Per-pixel noise statistics: each pixel's background-activity rate, ON and OFF apart, estimated from the stream.

A real DVS pixel fires without any change of light (leak and shot noise: ~0.1 Hz in bright light, up to a few Hz
in the dark, and a long tail of pixels far noisier than the rest). What counts as noise at a pixel is what it
fires while the scene is still there, so the counts are taken only over "still windows": the interval between
two consecutive APS frames counts at a pixel when (a) its 8 neighbours fired few events (at most
`neighbour_events`, raised when the sensor's noise alone gives more) and (b) its APS value changed by at most
`aps_tolerance_dn` + `aps_tolerance_rel` x the value. Both tests look away from the pixel's own events, so a
noisy pixel's rate is not biased by them; an edge that crosses the pixel fires its neighbours too, and a light
change shows in the APS, so neither inflates the rate. What still leaks in: moving low-contrast texture, whose
single threshold crossings (from a pixel's residual) look like noise (+40 % on moving blocks, docs/calibration.md).
Nothing is estimated while c is fixed (the reconstructor then forms no frame pairs).

The counts are the ones the c estimator's frame pairs already hold (ON/OFF events per pixel between two reference
times), so no extra pass over the events is made: the cost is one pass over the pixels per APS frame. With
exponential forgetting (time constant `memory_s`), per pixel and polarity:
    rate = (counts + prior_s * global) / (seconds + prior_s)
a Poisson rate shrunk towards the sensor-wide rate `global` (pooled over the pixels without outlying counts), so
a pixel watched for a second is not declared silent or noisy on one event. A pixel is noisy when its count is
significantly above what the global rate gives (4 sigma, Poisson) and its rate is at least `noisy_factor` times
the global rate. Pixels whose events are masked (hot, unreliable, flickering) are not updated: their counts are
not seen.

`PixelNoise` is the policy around that (when to update, what to report); `NoiseRates` is what a saved calibration
stores and a run starts from. numpy, and one numba kernel for the update (update_still_counts is its reference);
runs on the worker thread inside the reconstructor's on_frame. Statistics only: no frame depends on them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

import edi_live.edi as edi

PRIOR_S = 0.5  # weight of the sensor-wide rate in each pixel's estimate, in seconds of observation


@dataclass(frozen=True, eq=False)
class NoiseRates:
    """What was observed per pixel ((H, W) float32): the ON and OFF rates (Hz) over the still time `seconds`
    (0 Hz where a pixel was never still). These are the estimate's sufficient statistics, so that a saved
    calibration restarts exactly where it stopped; `estimate()` gives the rates the node reports."""

    on_hz: np.ndarray
    off_hz: np.ndarray
    seconds: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.on_hz.shape  # type: ignore[return-value]

    def estimate(self, prior_s: float = PRIOR_S) -> tuple[np.ndarray, np.ndarray]:
        """(ON Hz, OFF Hz) per pixel, each shrunk towards its sensor-wide rate (shrunk_rate, pooled_rate)."""
        sec = self.seconds.astype(np.float64)
        out = []
        for hz in (self.on_hz, self.off_hz):
            counts = hz * sec
            out.append(shrunk_rate(counts, sec, pooled_rate(counts, sec), prior_s))
        return out[0], out[1]


def neighbour_sum(counts: np.ndarray) -> np.ndarray:
    """(H, W): the sum of each pixel's 8 neighbours (outside the sensor counts 0)."""
    c = np.asarray(counts, np.int32)
    h, w = c.shape
    pad = np.zeros((h + 2, w + 2), np.int32)
    pad[1:-1, 1:-1] = c
    rows = pad[:-2] + pad[1:-1] + pad[2:]  # vertical 3-sums
    return rows[:, :-2] + rows[:, 1:-1] + rows[:, 2:] - c


def still_pixels(n_on: np.ndarray, n_off: np.ndarray, b_prev: np.ndarray, b_cur: np.ndarray, *,
                 neighbour_events: int, aps_tolerance_dn: float, aps_tolerance_rel: float) -> np.ndarray:
    """(H, W) bool: pixels where the scene was still between two APS frames: their 8 neighbours fired at most
    `neighbour_events` events and their APS value (linear DN) moved by at most tol_dn + tol_rel * value."""
    n = np.asarray(n_on).reshape(b_cur.shape) + np.asarray(n_off).reshape(b_cur.shape)
    quiet = neighbour_sum(n) <= neighbour_events
    tol = aps_tolerance_dn + aps_tolerance_rel * np.maximum(b_prev, b_cur)
    return quiet & (np.abs(b_cur - b_prev) <= tol)


def update_still_counts(on_acc: np.ndarray, off_acc: np.ndarray, seconds: np.ndarray, n_on: np.ndarray,
                        n_off: np.ndarray, b_prev: np.ndarray, b_cur: np.ndarray, masked: np.ndarray | None, *,
                        neighbour_events: int, aps_tolerance_dn: float, aps_tolerance_rel: float, decay: float,
                        interval_s: float) -> int:
    """In place, all (H, W) float64 accumulators: every pixel's counts and still time decay by `decay`, then the
    still pixels (still_pixels, not `masked`) add their ON/OFF counts and `interval_s`. Returns how many were
    still. The compiled kernel does the same in one pass over the pixels."""
    shape = b_cur.shape
    n_on, n_off = np.ascontiguousarray(n_on, np.int64).reshape(-1), np.ascontiguousarray(n_off, np.int64).reshape(-1)
    b_prev, b_cur = np.ascontiguousarray(b_prev, np.float32), np.ascontiguousarray(b_cur, np.float32)
    flat_mask = np.zeros(0, np.bool_) if masked is None else np.ascontiguousarray(masked, np.bool_).reshape(-1)
    if edi.have_numba():
        return int(_update_kernel(on_acc.reshape(-1), off_acc.reshape(-1), seconds.reshape(-1), n_on, n_off,
                                  b_prev, b_cur, flat_mask, int(neighbour_events), float(aps_tolerance_dn),
                                  float(aps_tolerance_rel), float(decay), float(interval_s)))
    still = still_pixels(n_on, n_off, b_prev, b_cur, neighbour_events=neighbour_events,
                         aps_tolerance_dn=aps_tolerance_dn, aps_tolerance_rel=aps_tolerance_rel)
    if flat_mask.size:
        still &= ~flat_mask.reshape(shape)
    for acc, n in ((on_acc, n_on.reshape(shape)), (off_acc, n_off.reshape(shape))):
        acc *= decay
        acc[still] += n[still]
    seconds *= decay
    seconds[still] += interval_s
    return int(np.count_nonzero(still))


@njit(cache=True, nogil=True)
def _update_kernel(on_acc, off_acc, seconds, n_on, n_off, b_prev, b_cur, mask, limit, tol_dn, tol_rel, decay, dt):
    h, w = b_cur.shape
    use_mask = mask.size > 0
    col = np.zeros(w + 2, np.int64)  # per column: the events of rows y-1..y+1 (padded by one column each side)
    still = 0
    for y in range(h):
        for x in range(w):
            v = n_on[y * w + x] + n_off[y * w + x]
            if y > 0:
                v += n_on[(y - 1) * w + x] + n_off[(y - 1) * w + x]
            if y + 1 < h:
                v += n_on[(y + 1) * w + x] + n_off[(y + 1) * w + x]
            col[x + 1] = v
        for x in range(w):
            q = y * w + x
            on_acc[q] *= decay
            off_acc[q] *= decay
            seconds[q] *= decay
            if use_mask and mask[q]:
                continue
            if col[x] + col[x + 1] + col[x + 2] - n_on[q] - n_off[q] > limit:
                continue
            bp, bc = b_prev[y, x], b_cur[y, x]
            if abs(bc - bp) > tol_dn + tol_rel * max(bp, bc):
                continue
            on_acc[q] += n_on[q]
            off_acc[q] += n_off[q]
            seconds[q] += dt
            still += 1
    return still


def shrunk_rate(counts: np.ndarray, seconds: np.ndarray, global_hz: float, prior_s: float) -> np.ndarray:
    """Per pixel: (counts + prior_s * global_hz) / (seconds + prior_s), a Poisson rate shrunk to the global one."""
    return ((counts + prior_s * global_hz) / (seconds + prior_s)).astype(np.float32)


def pooled_rate(counts: np.ndarray, seconds: np.ndarray) -> float:
    """The sensor-wide rate: pooled counts / pooled time, leaving out pixels whose count is far (5 sigma) above
    the first pooled estimate (the noisy tail would otherwise set everybody's prior). 0 when nothing was seen."""
    total_s = float(seconds.sum())
    if total_s <= 0:
        return 0.0
    first = float(counts.sum()) / total_s
    expected = first * seconds
    typical = counts <= expected + 5.0 * np.sqrt(expected) + 2.0
    typical_s = float(seconds[typical].sum())
    return float(counts[typical].sum()) / typical_s if typical_s > 0 else first


def noisy_pixels(counts: np.ndarray, seconds: np.ndarray, global_hz: float, factor: float,
                 prior_s: float) -> np.ndarray:
    """Bool per pixel: a count significantly (4 sigma, Poisson) above global_hz x seconds, and a shrunk rate at
    least `factor` x global_hz."""
    expected = global_hz * seconds
    rate = shrunk_rate(counts, seconds, global_hz, prior_s)
    return (counts > expected + 4.0 * np.sqrt(expected) + 2.0) & (rate >= factor * global_hz)


class PixelNoise:
    """Per-pixel ON/OFF noise rates with exponential forgetting, updated from each frame pair's counts.

    `enabled` False: nothing is estimated or reported. `fixed_hz`: every pixel's rate (ON + OFF) is that value,
    split evenly, and nothing is estimated. `start`: a saved estimate to start from (its still time counts, capped
    at `memory_s`)."""

    def __init__(self, width: int, height: int, *, enabled: bool = True, fixed_hz: float | None = None,
                 start: NoiseRates | None = None, memory_s: float = 60.0, prior_s: float = PRIOR_S,
                 neighbour_events: int = 2, aps_tolerance_dn: float = 4.0, aps_tolerance_rel: float = 0.1,
                 noisy_factor: float = 5.0, global_every: int = 25, summary_every: int = 100) -> None:
        self.width, self.height = width, height
        self.enabled = enabled
        self.fixed_hz = fixed_hz
        self.memory_s, self.prior_s, self.neighbour_events = memory_s, prior_s, neighbour_events
        self.aps_tolerance_dn, self.aps_tolerance_rel = aps_tolerance_dn, aps_tolerance_rel
        self.noisy_factor, self.global_every, self.summary_every = noisy_factor, global_every, summary_every
        shape = (height, width)
        self._on = np.zeros(shape, np.float64)  # decayed ON counts in still windows
        self._off = np.zeros(shape, np.float64)
        self._seconds = np.zeros(shape, np.float64)  # decayed still time
        if start is not None and start.shape == shape:
            sec = np.minimum(np.asarray(start.seconds, np.float64), memory_s)  # what forgetting would have left
            self._seconds[:] = sec
            self._on[:] = np.asarray(start.on_hz, np.float64) * sec
            self._off[:] = np.asarray(start.off_hz, np.float64) * sec
        self.global_on_hz = pooled_rate(self._on, self._seconds)
        self.global_off_hz = pooled_rate(self._off, self._seconds)
        self.updates = 0
        self.last_still = 0  # pixels still in the latest pair
        self._stale = False  # updated since the summary was computed
        self._summary: dict[str, float | int] = {}
        self._summary_at = 0  # `updates` when the summary was computed
        self._refresh()

    @property
    def active(self) -> bool:
        """Whether frame pairs are worth handing over (estimating, not fixed, not off)."""
        return self.enabled and self.fixed_hz is None

    def update(self, n_on: np.ndarray, n_off: np.ndarray, b_prev: np.ndarray, b_cur: np.ndarray,
               interval_us: int, mask: np.ndarray | None = None) -> None:
        """One pair of APS frames: the ON/OFF counts per pixel between their reference times (flat or (H, W)),
        their linear APS values, the interval's length, and the pixels whose events were masked."""
        if not self.active or interval_us <= 0:
            return
        dt = interval_us * 1e-6
        # the noise alone fires some neighbours: do not call a pixel busy for that
        lam = 8.0 * (self.global_on_hz + self.global_off_hz) * dt
        limit = max(self.neighbour_events, int(math.ceil(lam + math.sqrt(lam))))
        self.last_still = update_still_counts(
            self._on, self._off, self._seconds, n_on, n_off, b_prev, b_cur, mask, neighbour_events=limit,
            aps_tolerance_dn=self.aps_tolerance_dn, aps_tolerance_rel=self.aps_tolerance_rel,
            decay=math.exp(-dt / self.memory_s), interval_s=dt)
        self.updates += 1
        self._stale = True
        if self.updates <= 4 or self.updates % self.global_every == 0:  # the sensor-wide rates the next uses
            self._refresh_global()

    def rates(self) -> NoiseRates | None:
        """What was observed so far (None when off, or fixed: a fixed rate is a setting, not a calibration)."""
        if not self.active or not self._seconds.any():
            return None
        sec = np.maximum(self._seconds, 1e-12)
        return NoiseRates((self._on / sec).astype(np.float32), (self._off / sec).astype(np.float32),
                          self._seconds.astype(np.float32))

    def summary(self, current: bool = False) -> dict[str, float | int]:
        """noise_hz_p50 / noise_hz_p99 (ON + OFF, Hz per pixel), noise_on_hz_p50, noise_off_hz_p50, noisy_pixels;
        empty while off or before anything was seen. Computed on the caller's thread when asked for (3 ms at 240x180,
        7 ms at 346x260: percentiles over every pixel's rate), at most once per `summary_every` updates (5 s of a
        20 fps camera; the rates forget over a minute) unless `current` (the end of a run): the node's stats message
        asks every second, which on a still scene was most of the publisher thread's CPU. A figure may mix two
        updates, never more."""
        due = self._summary_at == 0 or self.updates - self._summary_at >= self.summary_every
        if self._stale and (current or due):
            self._refresh()
        return dict(self._summary)

    def _refresh_global(self) -> None:
        """The sensor-wide rates update() reads for its neighbour limit (two passes over the pixels)."""
        if self.active and self._seconds.any():
            self.global_on_hz = pooled_rate(self._on, self._seconds)
            self.global_off_hz = pooled_rate(self._off, self._seconds)

    def _refresh(self) -> None:
        self._stale = False
        self._summary_at = self.updates
        if not self.enabled:
            self._summary = {}
            return
        if self.fixed_hz is not None:
            hz = float(self.fixed_hz)
            self._summary = {"noise_hz_p50": hz, "noise_hz_p99": hz, "noise_on_hz_p50": hz / 2,
                             "noise_off_hz_p50": hz / 2, "noisy_pixels": 0}
            return
        if not self._seconds.any():
            self._summary = {}
            return
        # its own sensor-wide rates: update()'s stay on their schedule, whoever asks for a summary when
        g_on, g_off = pooled_rate(self._on, self._seconds), pooled_rate(self._off, self._seconds)
        on = shrunk_rate(self._on, self._seconds, g_on, self.prior_s)
        off = shrunk_rate(self._off, self._seconds, g_off, self.prior_s)
        # the percentiles of sorted copies: the same values (they depend on the multiset only), but numpy's sort
        # is ~4x faster than its selection on unsorted rates with few ties (a simulated sensor's)
        p50, p99 = np.percentile(np.sort(on + off, axis=None), [50, 99])
        noisy = noisy_pixels(self._on + self._off, self._seconds, g_on + g_off,
                             self.noisy_factor, self.prior_s)
        self._summary = {"noise_hz_p50": round(float(p50), 3), "noise_hz_p99": round(float(p99), 3),
                         "noise_on_hz_p50": round(float(median_of_sorted(np.sort(on, axis=None))), 3),
                         "noise_off_hz_p50": round(float(median_of_sorted(np.sort(off, axis=None))), 3),
                         "noisy_pixels": int(np.count_nonzero(noisy))}


def median_of_sorted(values: np.ndarray) -> np.floating:
    """np.median of a sorted 1-D array, without its selection pass: the mean of the middle one or two values, as
    numpy's median takes it (its mean of the middle slice), so the result is numpy's bit for bit (NaN with numpy's
    warning for no values; NaN when a value is NaN, which sorting puts last)."""
    if values.size and np.isnan(values[-1]):
        return values[-1]
    half = values.size // 2
    return np.mean(values[half:half + 1] if values.size % 2 else values[half - 1:half + 1])
