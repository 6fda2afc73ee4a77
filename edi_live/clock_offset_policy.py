"""When to estimate the event clock offset from the stream, and what to make of the estimates.

The math is edi_live.contrast.clock_offset (a fit on two consecutive frames, with the step model's lag taken out
first); this module owns the decision state: while an estimate is due it keeps the recent events (from the
reconstructor's on_events and on_frame, without duplicates) and the last two frames, fits the pair before the
newest frame once the events cover it with a margin, and after `per_round` estimates moves the offset to their
median when that differs from the current one by at least `min_change_us`. Rounds: at start-up, then every
`recheck_every` frames. A given offset (flag, TOML key, saved calibration) is never replaced.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from edi_live.contrast.clock_offset import FrameWindow, estimate_clock_offset, midlevel_times
from edi_live.datatypes import Frame
from edi_live.errors import ConfigError

MAX_OFFSET_US = 4000  # the search range, +-; the margin of events kept around each pair
MIDLEVEL_GAP_US = 20_000  # events kept before a window so that its events find their predecessors


@dataclass(frozen=True)
class ClockOffsetSettings:
    per_round: int = 4
    # pixels fire their first events from a fresh reference and without a predecessor: the first frames give a
    # lag of ~0.5 ms on the simulator (~0.1 ms later on)
    first_round_after: int = 5
    recheck_every: int = 1000  # a fit costs ~20 ms at 240x180 (~7 deblurs): rounds stay rare
    min_change_us: int = 100
    sample_pixels: int = 4000
    min_z: float = 3.0  # a pair's fit counts only when its best offset beats +-1 ms by this many standard errors


class ClockOffsetPolicy:
    """`collect(events)` with every event batch; `update(frame, ...)` per APS frame returns the new offset (µs)
    when it changed."""

    def __init__(self, given: int | None, width: int, height: int,
                 settings: ClockOffsetSettings = ClockOffsetSettings()) -> None:
        if given is not None and not (isinstance(given, int) and abs(given) <= 100_000):
            raise ConfigError(f"clock offset must be whole µs within +-100 ms (got {given!r})")
        self.given = given
        self.value = 0 if given is None else int(given)
        self.settings = settings
        self.width, self.height = width, height
        self.estimates = 0
        self.last_estimates: list[float] = []
        self._found: list[float] = []
        self._frames: list[FrameWindow] = []
        self._chunks: list[np.ndarray] = []
        self._t_max = -(2**63)
        self._frames_to_round = settings.first_round_after  # the stream start is atypical (see settings)
        sample = np.zeros(width * height, bool)
        keep = np.random.default_rng(20190617).choice(sample.size, min(sample.size, settings.sample_pixels),
                                                     replace=False)
        sample[keep] = True
        self._sample = sample.reshape(height, width)

    def frozen(self) -> "ClockOffsetPolicy":
        """A cheap copy that keeps the current offset and collects nothing (for a streaming copy)."""
        twin = copy.copy(self)
        twin.given = self.value
        return twin

    @property
    def estimated(self) -> bool:
        return self.given is None

    @property
    def collecting(self) -> bool:
        return self.given is None and self._frames_to_round <= 0

    def collect(self, events: np.ndarray) -> None:
        if not self.collecting or events.size == 0:
            return
        t = events["t"]
        if int(t[-1]) <= self._t_max:
            return
        new = events[np.searchsorted(t, self._t_max, "right"):]
        self._t_max = int(new["t"][-1])
        self._chunks.append(new[self._sample[new["y"], new["x"]]])  # the fit uses the sample's events only

    def update(self, frame: Frame, events: np.ndarray, image: np.ndarray, black_level: float,
               c: tuple[float, float], mask: np.ndarray | None) -> int | None:
        """One APS frame with its batch of events (exposure start to now, may overlap what was collected)."""
        if self.given is not None:
            return None
        self.collect(events)
        if not self.collecting:
            self._frames_to_round -= 1
            return None
        self._frames.append(FrameWindow(int(frame.exposure_start_us), int(frame.exposure_end_us),
                                        image.astype(np.float64), (image > black_level) & (image < 255)))
        self._frames = self._frames[-3:]
        if len(self._frames) < 3:
            return None
        prev, cur = self._frames[0], self._frames[1]  # the newest frame's events reach past cur's window
        events = np.concatenate(self._chunks) if self._chunks else None
        if events is None or events.size == 0:
            return None
        self._chunks = [events]
        if int(events["t"][0]) > prev.exposure_start_us - MAX_OFFSET_US - MIDLEVEL_GAP_US:
            return None  # collection began too late for this pair's events to find their predecessors
        keep_from = np.searchsorted(events["t"], cur.exposure_start_us - MAX_OFFSET_US - MIDLEVEL_GAP_US, "left")
        self._chunks = [events[keep_from:]]
        d = estimate_clock_offset(midlevel_times(events, self.width, MIDLEVEL_GAP_US), prev, cur, self._sample, c,
                                  black_level=black_level, mask=mask, max_offset_us=MAX_OFFSET_US,
                                  min_z=self.settings.min_z)
        if d is None:
            return None
        self.estimates += 1
        self._found.append(d)
        if len(self._found) < self.settings.per_round:
            return None
        median = int(round(float(np.median(self._found))))
        self.last_estimates, self._found = self._found, []
        self._frames, self._chunks, self._t_max = [], [], -(2**63)
        self._frames_to_round = self.settings.recheck_every
        if abs(median - self.value) < self.settings.min_change_us:
            return None
        self.value = median
        return median
