"""How long the worker lets a quiet stream pile up in the ring before reading it: a still camera's noise.

Owns the `WakeWhen` (edi_live.ring_wake) the worker waits with. While the latest events showed only background
noise (edi_live.activity), events make no frame: they only move the latent image, which comes out the same
whatever the size of the reads. A read per 1 ms packet then cost ~100 µs of wake-up and per-read bookkeeping for
~20 events (7 % of a core on a 240x180 sensor at 0.5 events/s per pixel), so the worker asks to be woken only
when `batch_us` of sensor time or more events than the noise explains have arrived (at most a latent frame's
worth, `every`, capped at MAX_EVENTS). An APS frame wakes it once its late events (the clock offset, frame_gate)
are in, since it could not be deblurred before, and is read with them; what came after the frame waits for the
next step, which starts there (`defer`). The end of the input and the deblur helper still wake it at once; the
heartbeat is its wait's timeout; an active scene is read as it comes, as before. On the noisy still scene at 20 fps
that is 2 reads per APS period (~42/s; 553/s with a step of a fifth of the period, each frame waking the worker
and its late window read per packet), and a read costs ~200 µs for ~500 events, per event mostly.

The price is at a motion onset: its first events are read at most `batch_us` of sensor time after they arrived.
`batch_us` is MAX_BATCH_US, or half the APS frame period when that is shorter, so the first frame after an onset
still comes within one frame period. Sooner in practice: the worker is woken once the events pushed exceed what the
noise gives in the time so far (its rate measured over the quiet waits) by SIGMAS Poisson deviations of a whole
step plus a margin, so an onset's extra events wake it early while noise alone rarely does (1.8-3.8 ms from the
first moving event to its frame in the lockstep test, sensor time; 2.0-6.8 ms when the count was that of a whole
step from its start). The rate starts at 0: the first quiet waits wake per packet until it is known.
"""

from __future__ import annotations

import dataclasses
import math

from edi_live.datatypes import Frame
from edi_live.ring import EventRing
from edi_live.ring_wake import WakeWhen

MAX_BATCH_US = 25_000
MIN_BATCH_US = 1_000
MAX_EVENTS = 1_000
SIGMAS, MARGIN = 4.0, 16


class QuietReads:
    def __init__(self, every: int) -> None:
        self.max_events = max(1, min(int(every), MAX_EVENTS))
        self.batch_us = MAX_BATCH_US
        self._last_aps_end_us: int | None = None
        self._mark: tuple[int, int] | None = None  # (head, watermark) at the previous quiet wait
        self._rate = 0.0  # noise events per µs of sensor time, averaged over the quiet reads
        self.batched_waits = 0  # waits with a WakeWhen (stats)
        self._last: WakeWhen | None = None  # the latest quiet wait's condition
        self._restart = False  # an APS frame was taken since: the quiet step starts again
        self._looked_at = -1  # the ring's head when the worker last went to wait
        self.frame_late_us: int | None = None  # the clock offset: an APS frame is not deblurred before its late events

    def on_aps_frame(self, frame: Frame, clock_offset_us: int = 0) -> None:
        """Learn the APS frame period (the onset delay is kept to half of it) and the event clock offset."""
        self.frame_late_us = int(clock_offset_us) if clock_offset_us > 0 else None
        self._restart = True
        end = frame.exposure_end_us
        if self._last_aps_end_us is not None and end > self._last_aps_end_us:
            period = end - self._last_aps_end_us
            self.batch_us = max(MIN_BATCH_US, min(MAX_BATCH_US, period // 2))
        self._last_aps_end_us = end

    def wake(self, ring: EventRing, quiet: bool, held_through_us: int | None = None) -> WakeWhen | None:
        """The condition to wait with once the worker has nothing to do; None (wake per push) unless the scene is
        `quiet`. `held_through_us`: the worker holds the first queued APS frame until it has read an event later
        than this (its late events, frame_gate); the queued frames then wake it only once the sensor time is past
        that (a wake per 1 ms packet through an 8 ms clock offset was a third of a still scene's reads). A new APS
        frame wakes it once its own late events are in (at once without a clock offset)."""
        if not quiet:
            self._mark = self._last = None
            return None
        head, t_us = ring.read_index, ring.watermark_us  # (events pushed since the last read count towards it)
        pushed = ring.head  # the rate from what was pushed, not read: reads left for a later step do not bias it
        if self._mark is not None and t_us > self._mark[1]:
            rate = (pushed - self._mark[0]) / (t_us - self._mark[1])
            self._rate = rate if not self._rate else 0.75 * self._rate + 0.25 * rate
        self._mark = (pushed, t_us)
        self._looked_at, self._restart = pushed, False  # the step below starts after any APS frame taken
        self.batched_waits += 1
        self._last = step = self._step_from(head, t_us, pushed, ring.max_unread)
        due_us = step.t_us
        if held_through_us is not None:  # (if the watermark is past it already but no event is, the next packet)
            due_us = min(due_us, max(held_through_us + 1, t_us + 1))
        return dataclasses.replace(step, t_us=due_us, frames=int(held_through_us is not None),
                                   frame_late_us=self.frame_late_us)

    def _step_from(self, head: int, t_us: int, pushed: int, max_unread: int) -> WakeWhen:
        """A step of batch_us from read index `head` at watermark `t_us`; `pushed`: the ring's head then. Its count
        stays within half of what the ring lets pile up unread: a producer waiting for room could never meet it."""
        expected = self._rate * self.batch_us
        slack = SIGMAS * math.sqrt(expected) + MARGIN
        count = max(1, min(self.max_events, int(expected + slack), max_unread // 2))
        return WakeWhen(head=head + count, t_us=t_us + self.batch_us, rate_per_us=self._rate, head0=pushed,
                        t0_us=t_us, slack=slack)

    def defer(self, ring: EventRing) -> bool:
        """Whether to leave the unread events for the next step: the worker was woken for an APS frame (what came
        after the frame and its late events, ~1 ms, was a read of its own). A step starts after each APS frame,
        unless the one under way is met (the worker was woken for it): else, as steps and frames fall into step,
        a step ending with the frame's late window read that ms. Nothing is deferred once nothing was pushed since
        the worker went to wait (it timed out: a source that pauses without closing), nor past half of what the
        ring lets pile up unread."""
        last, pushed = self._last, ring.head
        if last is None or ring.closed or pushed == self._looked_at or ring.unread_events >= ring.max_unread // 2:
            self._restart = False
            return False
        if self._restart:  # an APS frame was taken since the worker last waited: the step starts after it
            self._last = last = self._step_from(ring.read_index, ring.watermark_us, pushed, ring.max_unread)
            self._restart = False
        return not last.met(pushed, ring.watermark_us)
