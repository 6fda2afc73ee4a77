"""The calibration work of each APS frame, split into what the frame's deblur needs and what can wait until the
deblurred frame has left (`settle`).

Before the deblur: this frame's data and its pair with the previous frame (contrast_tracking; the pair also serves
the unreliable-pixel test of this deblur, unless the clock offset moved since the previous frame). After it, on
`settle()`, in the order the reconstructor ran them before settle() existed: the c policy's decision on the new
pair (fit test, re-estimation), the black level policy, the clock offset policy's registration of the frame (with
the c and black level just decided, as before) and the pixel-noise statistics. A pair the c policy finds still
(its events explain no brightness change) goes to neither the black level nor the clock offset: it holds nothing
either could learn from, and on a still scene their start-up fits (~10 ms a frame) would run on every heartbeat.
What settle decides takes effect at the next frame: c and the black level never change between two frames, and a
frame is deblurred with the values in force before it. At start-up (no c estimated yet, also after a black-level
restart) the c decision stays before the deblur that needs it. (A new clock offset is in use from the next frame
on; its pairs start there.)
Once the calibration has settled, the c fit test and the level tables it reads run on fewer frames
(calibration_schedule: which frames, and why the other parts are not thinned).

Owned by one EdiReconstructor; runs on whatever thread runs its on_frame / settle (never two at once).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.black_level_policy import BlackLevelPolicy
from edi_live.calibration_schedule import CalibrationSchedule, ScheduleSettings
from edi_live.c_policy import ContrastPolicy
from edi_live.clock_offset_policy import ClockOffsetPolicy
from edi_live.contrast_tracking import ContrastTracker
from edi_live.datatypes import Frame
from edi_live.pixel_noise import PixelNoise


@dataclasses.dataclass
class _Due:
    """One frame's work left for settle()."""

    cur: contrast.FrameData
    pairs: list[contrast.FramePair] | None  # None: the c policy already ran before the deblur (start-up)
    pair: contrast.FramePair | None  # the pair formed on the frame (before a clock offset change dropped it)
    black_taken_off: float
    clock: tuple  # clock.update's arguments but the black level and c: (frame, events, image, mask)
    moved: bool  # the clock offset changed since the previous frame: its windows are not the pairs' before
    noise: tuple | None = None  # pixel_noise.update's arguments, once the deblur has set them


class FrameCalibration:
    """`before_deblur` per frame, `after_deblur` once the frame is deblurred, `settle` when the frame has left."""

    def __init__(self, policy: ContrastPolicy, tracker: ContrastTracker, black: BlackLevelPolicy,
                 clock: ClockOffsetPolicy, pixel_noise: PixelNoise, settled_check_every: int = 1) -> None:
        self.policy, self.tracker, self.black, self.clock, self.pixel_noise = policy, tracker, black, clock, pixel_noise
        # thinned only where nothing else counts frames between estimates (reestimate_every) or pools pairs (joint)
        every = settled_check_every if not (policy.settings.reestimate_every or policy.pools_pairs) else 1
        self.schedule = CalibrationSchedule(ScheduleSettings(c_every=every))
        self.tests_skipped = 0  # frames whose c fit test the schedule left out
        self._due: _Due | None = None
        self._black_next: float | None = None  # decided by settle, used from the next frame on
        self._offset_used: int | None = None  # the clock offset of the previous frame
        self.last_settle_ms = 0.0

    @property
    def pending(self) -> bool:
        return self._due is not None

    def before_deblur(self, frame: Frame, events: np.ndarray, img: np.ndarray, aps: edi.ApsResponse,
                      window: tuple[int, int, int], mask: np.ndarray | None, acc: tuple[np.ndarray, np.ndarray],
                      t_last: int, has_reference: bool) -> tuple[contrast.FramePair | None, edi.ApsResponse]:
        """(the pair formed on this frame, None if there is none or it was dropped; the APS response to deblur
        with). `acc` (the counts applied since the previous f) becomes the pair's counts, changed in place.
        Call settle() first: a frame must not start while the previous one's work is pending."""
        moved = self._offset_used is not None and self.clock.value != self._offset_used
        self._offset_used = self.clock.value
        if self._black_next is not None:
            aps, self._black_next = dataclasses.replace(aps, black_level=self._black_next), None
        b, informative = aps.to_float(img)
        raw = edi.blurry_to_float(img, saturation=aps.saturation)[0] if aps.black_level and self.black.estimated else None
        cur, pair = self.tracker.step(events, b, informative, window, mask, acc, t_last, has_reference, raw)
        pairs = self.tracker.pairs
        if not self.policy.estimated:  # start-up: this deblur needs the first estimate
            self.tracker.complete()
            self.policy.update(cur, pairs)
            pairs = None
        self._due = _Due(cur, pairs, pair, aps.black_level, (frame, events, img, mask), moved)
        return (None if moved else pair), aps  # a pair across an offset change is not judged

    def after_deblur(self, pair: contrast.FramePair | None, dt_us: int, mask: np.ndarray | None) -> None:
        """The deblurred frame's pair (as before_deblur returned it) for the noise statistics."""
        if self._due is not None and pair is not None:
            self._due.noise = (pair.n_on, pair.n_off, pair.prev.blurry, pair.cur.blurry, dt_us, mask)

    def settle(self) -> None:
        """The pending work of the latest frame: the c decision, the black level, the noise statistics; which of
        the steady-state checks run on this frame is the schedule's (calibration_schedule)."""
        due, self._due = self._due, None
        if due is None:
            return
        t0 = time.perf_counter()
        plan = self.schedule.plan()
        if plan.c_test or self.black.samples():
            self.tracker.complete()  # the frame's level table: the policies below read it, the deblur did not
        before = (self.policy.reestimations, self.policy.events_ignored, self.clock.value)
        if due.pairs is not None:
            if plan.c_test:  # (an estimate after a failed test uses the pairs whose tables were built)
                self.policy.update(due.cur, [p for p in due.pairs if p.has_tables])
            else:
                self.policy.skip()
                self.tests_skipped += 1
        frame, events, img, mask = due.clock
        new_black = None
        if self.policy.events_ignored:  # the pair's events carry no signal: nothing to learn the black level or
            self.clock.still(events)    # the clock offset from (a still scene would spend its start-up fits here)
        else:
            new_black = self.black.update(due.pair, due.black_taken_off)
            black = due.black_taken_off if new_black is None else new_black
            self.clock.update(frame, events, img, black, self.policy.c, mask)
        if new_black is not None:  # pairs so far used the old value; c is estimated afresh
            self._black_next = new_black
            self.tracker.restart()
        elif due.moved:
            self.tracker.windows_moved()  # pairs so far used the old offset; this frame opens the next one
        elif due.noise is not None:
            self.pixel_noise.update(*due.noise)
        changed = (due.pairs is None or due.pair is None or new_black is not None or due.moved
                   or (self.policy.reestimations, self.policy.events_ignored, self.clock.value) != before)
        # a still verdict is not thinned: its test is what brings the events back once the scene moves again
        self.schedule.observe(not changed and self.policy.settled and not self.policy.events_ignored, changed)
        if self.schedule.plan().c_test or self.black.samples():
            self.tracker.complete()  # the next frame's fit test (or the black level's sample) reads this frame's
        self.last_settle_ms = (time.perf_counter() - t0) * 1e3
