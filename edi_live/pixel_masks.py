"""Which events the reconstructor trusts: the hot-pixel mask from decaying per-pixel event rates, and the optional
background-activity filter (an event counts only if a neighbour fired within `window_us` of it).

State per sensor: decaying counts and the current mask (hot pixels), the latest event time per pixel (filter).
Runs on the worker thread; plain numpy state, the math is edi_live.edi's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import edi_live.edi as edi


class HotPixels:
    """A pixel is hot when its decayed event rate is high both absolutely and against the active pixels' mean
    (edi.hot_pixel_mask). The mask found after an exposure is used from the next frame on."""

    def __init__(self, width: int, height: int, *, enabled: bool, min_rate_hz: float, rel_factor: float,
                 decay: float) -> None:
        self.enabled = enabled
        self._shape = (height, width)
        self._min_rate_hz, self._rel_factor, self._decay = min_rate_hz, rel_factor, decay
        npix = width * height
        self._counts = np.zeros(npix, np.float64)
        self.frame_counts = np.zeros(npix, np.int64)  # this exposure's events per pixel, filled by the deblur pass
        self._duration_us = 0.0
        self._mask = np.zeros(self._shape, bool)

    @property
    def mask(self) -> np.ndarray | None:
        """The (H, W) bool mask to apply, or None when masking is off. Replaced, never changed in place."""
        return self._mask if self.enabled else None

    def snapshot(self) -> np.ndarray:
        """A copy of the current mask (all False when masking is off and nothing was ever found)."""
        return self._mask.copy()

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self._mask))  # ~2 µs at 240x180, sum() of a bool mask ~13

    def end_exposure(self, exposure_us: int) -> None:
        """Fold this exposure's frame_counts into the decaying counts (resetting them) and update the mask."""
        self._duration_us = self._duration_us * self._decay + exposure_us
        hot = edi.decay_hot_counts(self._counts, self.frame_counts, self._decay, self._duration_us,
                                   min_rate_hz=self._min_rate_hz, rel_factor=self._rel_factor)
        self._mask = hot.reshape(self._shape)


class NoiseFilter:
    """Background-activity filter over the event stream. The state sees every event once, in time order."""

    def __init__(self, width: int, height: int, window_us: int) -> None:
        self.width, self.height, self.window_us = width, height, int(window_us)
        self._last_t = edi.new_activity_map(width, height)

    def copy(self) -> "NoiseFilter":
        twin = NoiseFilter.__new__(NoiseFilter)
        twin.width, twin.height, twin.window_us = self.width, self.height, self.window_us
        twin._last_t = self._last_t.copy()
        return twin

    def stream(self, events: np.ndarray) -> np.ndarray:
        """The events (after everything seen so far) with a neighbour event within window_us before them."""
        return events[edi.background_activity_keep(events, self.width, self.height, self._last_t, self.window_us)]

    def exposure(self, events: np.ndarray, seen_until_us: int) -> np.ndarray:
        """For a whole exposure's batch: the state first sees the events after `seen_until_us`; the result keeps
        the events with a neighbour event within window_us before OR after them (isolated ones are most likely
        noise)."""
        fresh = events[edi.time_index(events["t"], seen_until_us, "right"):]
        edi.background_activity_keep(fresh, self.width, self.height, self._last_t, self.window_us)
        return events[edi.supported_events_keep(events, self.width, self.height, self.window_us)]


class UnreliablePixels:
    """Pixels whose events contradict the APS frames: between two consecutive frames their events predict a log
    change that the frames do not show (mains flicker with ON/OFF bursts that do not cancel, OFF events lost to
    the refractory period, a pixel stuck firing one polarity). Their events are then ignored like a hot pixel's,
    so the latent image keeps what the APS says there instead of blooming or drifting.

    Evidence per pair of frames k, k+1, at pixels with at least `min_events` events between f_k and f_k+1:
    predicted = c_on*n_on - c_off*n_off, observed = log L_k+1(f_k+1) - log L_k(f_k), the deblurred references (the
    consistency that the c estimator fits on a sample, checked here at every pixel). Contradiction: a large
    predicted change (>= `min_change` in log units) of which the frames show less than 1 - `relative`, where both
    frames are informative, or |predicted| > `saturated_limit` where either is clipped (the APS cannot confirm a
    change that large). A decaying score (x `decay` per pair,
    +1 per contradiction) marks a pixel while it is >= 1 and frees it below `release`. Moving edges explain their
    frames (the residual of a correct c is small next to the change itself), so they stay."""

    def __init__(self, width: int, height: int, *, min_events: int = 3, min_change: float = 2.5,
                 relative: float = 0.9, saturated_limit: float = 4.0, decay: float = 0.8,
                 release: float = 0.2, grow_px: int = 0) -> None:
        self._shape = (height, width)
        self._grow = [(dy, dx) for dy in range(-grow_px, grow_px + 1) for dx in range(-grow_px, grow_px + 1)
                      if dy * dy + dx * dx <= grow_px * grow_px + grow_px]  # a disk of that radius
        self._grow_array = np.array(self._grow, np.int64).reshape(-1, 2)  # not converted again per frame
        self.min_events, self.min_change, self.relative = min_events, min_change, relative
        self.saturated_limit, self.decay, self.release = saturated_limit, decay, release
        self._score = np.zeros(width * height, np.float32)
        self._own = np.zeros(self._shape, bool)  # pixels marked on their own evidence
        self._mask = self._own

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool; replaced, never changed in place."""
        return self._mask

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self._mask))  # ~2 µs at 240x180, sum() of a bool mask ~13

    def update(self, n_on: np.ndarray, n_off: np.ndarray, log_prev: np.ndarray, log_cur: np.ndarray,
               informative_prev: np.ndarray, informative_cur: np.ndarray, c: tuple[float, float],
               busy: np.ndarray | None = None) -> None:
        """One pair of frames: counts (flat) between their reference times, their log L(f) and their informative
        masks (B neither black nor clipped). A marked pixel's events are ignored, so its counts say nothing: while
        it keeps firing (`busy`, flat: its events in the latest exposure, masked or not, at least min_events), its
        score is held rather than decayed, so a flickering lamp stays marked instead of blooming again each time
        the score would have run out."""
        own = edi.update_contradictions(
            self._score, self._own, n_on, n_off, log_prev, log_cur, informative_prev, informative_cur, c, busy,
            min_events=self.min_events, min_change=self.min_change, relative=self.relative,
            saturated_limit=self.saturated_limit, decay=self.decay, release=self.release).reshape(self._shape)
        self._own = own
        if len(self._grow) > 1 and own.any():
            # a lamp's halo contradicts the frames less clearly than its core, but just as surely
            own = edi.dilate(own, self._grow_array)  # ~0.17 ms as 21 numpy shifts at 240x180, ~0.02 compiled
        self._mask = own


def combined_mask(hot: HotPixels, unreliable: "UnreliablePixels | None", flicker_pixels: Any,
                  flicker: np.ndarray | None = None) -> np.ndarray | None:
    """(H, W) bool: the pixels whose events are ignored (hot, unreliable, flickering), or None when there are none.
    `flicker`: the flicker mask to use (default: the detector's latest, `flicker_pixels`, if it flags any pixel)."""
    if flicker is None and flicker_pixels is not None and flicker_pixels.count:
        flicker = flicker_pixels.mask
    masks = [m.mask for m in (unreliable,) if m is not None and m.count] + [flicker]
    masks = [m for m in [hot.mask] + masks if m is not None]
    if len(masks) < 2:
        return masks[0] if masks else None
    out = np.logical_or(masks[0], masks[1])  # pairwise: logical_or.reduce stacks the list into one array first
    for m in masks[2:]:
        np.logical_or(out, m, out=out)
    return out
