"""Which events the reconstructor trusts: the hot-pixel mask from decaying per-pixel event rates, and the optional
background-activity filter (an event counts only if a neighbour fired within `window_us` of it).

State per sensor: decaying counts and the current mask (hot pixels), the latest event time per pixel (filter).
Runs on the worker thread; plain numpy state, the math is edi_live.edi's.
"""

from __future__ import annotations

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
        return int(self._mask.sum())

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
