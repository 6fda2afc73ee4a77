"""When to estimate the event clock offset from the stream, and what to make of the estimates.

The math is edi_live.contrast.clock_offset (a fit on two consecutive frames, with the step model's lag taken out
first); this module owns the decision state. While a round is on it keeps the sample pixels' recent events (from
the reconstructor's on_events and on_frame, without duplicates) and the frames; each new frame makes the pair it
closes due. `update` runs in the reconstructor's settle(), after the frame's deblur has been sent (on the deblur
thread when the worker has one, never between latent frames): it registers the frame and fits the due pairs whose
windows the kept events cover with the search margin, in practice the pair before, one frame later. A new value is
in `value` at once, so the next frame's window uses it (edi_live.frame_calibration then drops the frame pairs
formed with the old value, and that frame, taken with the new windows, opens the next pair). The round ends with `agree` consecutive fits within `agree_us` of each other (their
mean) or with `per_round` fits (their median), or without a change after `max_fits` fits; the offset moves when
the result differs from the current one by at least `min_change_us`. Rounds: from the first frame, then every
`recheck_every` frames. A given offset (flag, TOML key) is never replaced; a starting one (a saved calibration's)
is in use from the first frame and moves like an estimate, unless it lies beyond +-MAX_OFFSET_US, where no fit can
reach: then it is given. Everything depends
only on the calls' order and contents (no clock, no thread).

Two values come out of each round. `physical_us` is the camera's own offset: the fit with the whole step lag taken
out (recovered within 0.3 ms on the simulator). `value`, the offset in use for the exposure windows, is the same fit
keeping `use_lag_share` of the lag: EDI's deblur and latent frames use the same step model, so they lag too, and
windows moved by half the lag scored best against ground truth (ideal scenes +0.16 / +0.29 dB, docs/calibration.md).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from edi_live.contrast.clock_offset import FrameWindow, clock_offset_fit, pixel_polarity_key
from edi_live.datatypes import Frame
from edi_live.errors import ConfigError

MAX_OFFSET_US = 8000  # the search range, +-; the margin of events needed after each pair (real DAVIS346: 1-6 ms)
MIDLEVEL_GAP_US = 20_000  # events kept before a pair so that its events find their predecessors; the gaps' cap


@dataclass(frozen=True)
class ClockOffsetSettings:
    agree: int = 2  # this many consecutive fits ...
    # ... this close together end a round (their mean): the fits of a pair scatter by ~+-200 µs on an ideal camera
    # and more with a real one's effects (astronaut fast: 1831 and 1508 µs for a true 1500, the round ran two more
    # frames at 300)
    agree_us: int = 400
    per_round: int = 4  # else a round ends after this many fits (their median)
    max_fits: int = 8  # or, short of that, after this many pairs fitted (each costs a few ms): no change
    recheck_every: int = 1000
    min_change_us: int = 200  # a pair's fit scatters by ~+-200 µs (ideal camera): smaller moves are noise
    # pixels whose events are kept; a fit uses up to fit_pixels of them that have events (3000 let no fit pass on
    # the sparse real recordings; 20000 finds emlb's offset)
    sample_pixels: int = 20000
    fit_pixels: int = 3000
    min_z: float = 2.0  # a pair's fit counts only when its best offset beats +-1 ms by this many standard errors
    # the offset in use keeps this share of EDI's step lag (0: all of it, as a fit without the midlevel
    # correction finds; 1: none, the camera's own offset): 0.5 scored best against ground truth (calibration.md)
    use_lag_share: float = 0.5


@dataclass(frozen=True)
class _Due:
    """A frame pair waiting for its fit, with the calibration of the moment it closed."""

    prev: FrameWindow
    cur: FrameWindow
    black_level: float
    c: tuple[float, float]
    mask: np.ndarray | None

    def runnable(self, t_max: int) -> bool:
        """Whether events up to t_max complete the fit's data (the search margin past the newer exposure)."""
        return t_max >= self.cur.exposure_end_us + MAX_OFFSET_US


class ClockOffsetPolicy:
    """`collect(events)` with every event batch (keeps them); `update(frame, ...)` per APS frame registers it and
    runs the due fits, or `still(events)` for a frame whose pair is still; `value` is the offset (µs) in use."""

    def __init__(self, given: int | None, width: int, height: int,
                 settings: ClockOffsetSettings = ClockOffsetSettings(), *, start: int | None = None) -> None:
        for what, v in (("clock offset", given), ("starting clock offset", start)):
            if v is not None and not (isinstance(v, int) and abs(v) <= 100_000):
                raise ConfigError(f"{what} must be whole µs within +-100 ms (got {v!r})")
        if given is None and start is not None and abs(start) > MAX_OFFSET_US:
            given = start  # beyond the search range: a fit could only replace it with the range's edge
        self.given = given
        # in use: the camera's offset plus the kept step lag; until a round moves it, `start` (a saved calibration's)
        self.value = int(given if given is not None else (start or 0))
        self.physical_us = self.value  # the camera's own offset (events late against the APS exposure)
        self.from_calibration = given is None and start is not None  # the start is in use, no round ended yet
        self.settings = settings
        self.width, self.height = width, height
        self.estimates = 0
        self.fits_run = 0
        self.last_estimates: list[float] = []
        self._found: list[float] = []  # this round's fits: the camera's offset ...
        self._found_in_use: list[float] = []  # ... and with the kept share of the step lag
        self._end_round()
        self._frames_to_round = 0  # the first round starts with the stream
        self._paused = False  # a still scene: nothing collected until a frame moves (`still`)
        sample = np.zeros(width * height, bool)
        keep = np.random.default_rng(20190617).choice(sample.size, min(sample.size, settings.sample_pixels),
                                                     replace=False)
        sample[keep] = True
        self._sample = sample.reshape(height, width)

    def frozen(self) -> "ClockOffsetPolicy":
        """A cheap copy that keeps the current offset and collects nothing (for a streaming copy)."""
        twin = copy.copy(self)
        twin._frames_to_round = 2**62  # never collects; `given` stays, so an estimated offset still reads so
        twin._due, twin._chunks, twin._found, twin._found_in_use = [], [], [], []  # nothing shared: it goes on
        return twin

    @property
    def estimated(self) -> bool:
        return self.given is None

    @property
    def collecting(self) -> bool:
        return self.given is None and self._frames_to_round <= 0

    @property
    def due(self) -> int:
        """Frame pairs waiting for their fit."""
        return len(self._due)

    def collect(self, events: np.ndarray) -> None:
        """Keep the sample's new events (the fits run in update, off the stream of latent frames); not while the
        scene is still (`still`): the next frame that moves brings its exposure's events itself."""
        if self.collecting and not self._paused:
            self._keep(events)

    def update(self, frame: Frame, events: np.ndarray, image: np.ndarray, black_level: float,
               c: tuple[float, float], mask: np.ndarray | None) -> None:
        """One APS frame with its batch of events (exposure start to now, may overlap what was collected): it
        closes a pair, and the due pairs the kept events now cover are fitted here (the reconstructor's settle)."""
        if not self._in_round():
            return
        self._paused = False
        if self._last is not None and frame.exposure_start_us <= self._last.exposure_start_us:
            self._drop_data()  # time went backwards (a recording looped): what was kept belongs to another stream
        self._keep(events)
        window = FrameWindow(int(frame.exposure_start_us), int(frame.exposure_end_us), image.astype(np.float64),
                             (image > black_level) & (image < 255))
        if self._last is not None:
            self._due = self._due[-1:] + [_Due(self._last, window, float(black_level), tuple(c), mask)]
        self._last = window
        self._fit_runnable()

    def still(self, events: np.ndarray) -> None:
        """An APS frame whose pair with the previous one is still (the c policy ignores its events), with its batch
        of events: it says nothing about the offset, so no pair is formed across it. The moving pair before it, if
        waiting for its fit, is fitted now when the events cover it (the verdict is on the newest pair only); then
        the kept events are dropped, and none are kept until a frame that moves comes to `update`. The round stays
        open: its fits come with the frames that move."""
        if not self._in_round():
            return
        if self._due:
            self._keep(events)
            self._fit_runnable()
        if self.collecting:  # (unless that fit ended the round)
            self._drop_data()
            self._paused = True

    # ---- internals ----

    def _in_round(self) -> bool:
        """Whether an APS frame counts for a round (estimated, and collecting); between rounds it counts down to
        the next one."""
        if self.given is not None:
            return False
        if not self.collecting:
            self._frames_to_round -= 1
            return False
        return True

    def _fit_runnable(self) -> None:
        """Fit the due pairs the events kept so far complete."""
        while self._due and self._due[0].runnable(self._t_max):
            self._fit(self._due.pop(0))

    def _keep(self, events: np.ndarray) -> None:
        if not self.collecting or events.size == 0:
            return
        t = events["t"]
        if int(t[-1]) < self._t_max:
            return
        # batches overlap (an exposure's window, a batch handed on twice) or continue one another, possibly in the
        # middle of a group of events with the newest time: those are told apart by pixel and polarity
        i, j = np.searchsorted(t, self._t_max, "left"), np.searchsorted(t, self._t_max, "right")
        group = events[i:j]  # (empty when a batch continues the last: no isin, ~10 µs a read on a quiet stream)
        fresh = group[~np.isin(self._pixel_key(group), self._at_max)] if i < j else group
        rest = events[j:]
        if rest.size:
            self._t_max = int(rest["t"][-1])
            self._at_max = self._pixel_key(rest[np.searchsorted(rest["t"], self._t_max, "left"):])
        elif fresh.size:
            self._at_max = np.union1d(self._at_max, self._pixel_key(fresh))
        for part in (fresh, rest):
            if part.size:
                self._chunks.append(part[self._sample[part["y"], part["x"]]])  # the fit uses the sample's only

    def _pixel_key(self, events: np.ndarray) -> np.ndarray:
        return pixel_polarity_key(events, self.width)

    def _fit(self, due: _Due) -> None:
        if not self._chunks:
            return
        events = np.concatenate(self._chunks) if len(self._chunks) > 1 else self._chunks[0]
        t = events["t"]
        # events the next pairs need stay (with their predecessors' history); the fit sees only up to its margin,
        # so that its result does not depend on how far the batches happened to reach
        self._chunks = [events[np.searchsorted(t, due.cur.exposure_start_us - MAX_OFFSET_US - MIDLEVEL_GAP_US):]]
        events = events[np.searchsorted(t, due.prev.exposure_start_us - MAX_OFFSET_US - MIDLEVEL_GAP_US):
                        np.searchsorted(t, due.cur.exposure_end_us + MAX_OFFSET_US, "right")]
        self.fits_run += 1
        self._fits_in_round += 1
        s = self.settings

        fit = clock_offset_fit(events, due.prev, due.cur, self._sample, due.c, black_level=due.black_level,
                               mask=due.mask, max_offset_us=MAX_OFFSET_US, midlevel_gap_us=MIDLEVEL_GAP_US,
                               complete_until_us=due.cur.exposure_end_us + MAX_OFFSET_US, max_pixels=s.fit_pixels,
                               min_z=s.min_z)  # the second share reuses the first's pixels and event shifts
        d = fit(1.0)
        if d is None:
            if self._fits_in_round >= s.max_fits:  # these frames say nothing: keep the offset, ask again later
                self._end_round()
            return
        in_use = fit(s.use_lag_share) if s.use_lag_share != 1.0 else d
        self.estimates += 1
        self._found.append(d)
        self._found_in_use.append(d if in_use is None else in_use)
        recent = self._found[-s.agree:]
        if len(recent) >= s.agree and max(recent) - min(recent) <= s.agree_us:
            found, found_in_use = float(np.mean(recent)), float(np.mean(self._found_in_use[-s.agree:]))
        elif len(self._found) >= s.per_round:
            found, found_in_use = float(np.median(self._found)), float(np.median(self._found_in_use))
        else:
            if self._fits_in_round >= s.max_fits:
                self._end_round()
            return
        self.last_estimates = self._found
        self.from_calibration = False
        self._end_round()
        new = int(round(found_in_use))
        self.physical_us = int(round(found))
        if abs(new - self.value) >= s.min_change_us:
            self.value = new

    def _end_round(self) -> None:
        self._found, self._found_in_use = [], []
        self._fits_in_round = 0
        self._drop_data()
        self._frames_to_round = self.settings.recheck_every

    def _drop_data(self) -> None:
        self._due: list[_Due] = []
        self._last: FrameWindow | None = None
        self._chunks: list[np.ndarray] = []
        self._t_max = -(2**63)
        self._at_max = np.zeros(0, np.int64)  # pixel keys of the kept events at _t_max
