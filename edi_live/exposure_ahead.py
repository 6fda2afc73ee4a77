"""Deblurring ahead of the exposure end: predict the next APS exposure window from the last ones and accumulate its
double integral while its events arrive (edi.RunningDivisor), so that at exposure end only a finish over the active
pixels remains.

The worker learns a frame's exposure window only with the frame, after the exposure has ended (a DAVIS sends the
pixels after the exposure; replay hands the frame after its events). Exposures are regular, though (a fixed
exposure every frame interval), so the next one is predicted from the last three. The prediction is used only if
it turns out exact, with the same c, mask and count array as the deblur then has, and if no event of the predicted
window was seen before the running integral started; otherwise the deblur reads the exposure's events as before.
Either way the frame is the same, bit for bit (edi.RunningDivisor). Policy only: the math is edi.RunningDivisor.
"""

from __future__ import annotations

import collections

import numpy as np

import edi_live.edi as edi


class ExposureAhead:
    """When to run the next exposure's double integral ahead, and its running state (owned by one reconstructor)."""

    def __init__(self, width: int, height: int, enabled: bool = True) -> None:
        self.width, self.height, self.enabled = width, height, enabled
        self._windows: collections.deque[tuple[int, int]] = collections.deque(maxlen=3)
        self._running: edi.RunningDivisor | None = None
        self.used = 0  # deblurs finished from the running integral
        self.missed = 0  # deblurs that read the events at exposure end although a prediction was running
        self.remasked = 0  # of the used ones, those whose mask changed on the way (running integral re-masked)

    def arm(self, ts: int, te: int, c: tuple[float, float], mask: np.ndarray | None,
            event_counts: np.ndarray | None, seen_until: int) -> None:
        """After the deblur of the exposure [ts, te]: start the next one's integral if its window is predictable
        and none of its events has been seen yet (`seen_until`: the latest event time handed over so far)."""
        self._windows.append((int(ts), int(te)))
        self._running = None
        if not self.enabled or len(self._windows) < 3:
            return
        (s0, e0), (s1, e1), (s2, e2) = self._windows
        period = s2 - s1
        if period <= 0 or s1 - s0 != period or e2 - s2 != e1 - s1 or e1 - s1 != e0 - s0:
            return  # not regular: nothing to predict
        nts, nte = s2 + period, e2 + period
        if nts <= seen_until:
            return  # the next exposure has begun: its first events went by before this integral existed
        self._running = edi.RunningDivisor(self.width, self.height, nts, nte, (nts + nte) // 2, c[0], c[1],
                                           mask=mask, event_counts=event_counts)

    def rearm(self, c: tuple[float, float]) -> None:
        """The next deblur will use c after all (the c policy decided after arm()): start the integral again with
        it, if no event was fed yet (otherwise the deblur reads the events at the end, as on any mismatch)."""
        r = self._running
        if r is None or r.fed_until > -(2**63) or (r.c_on, r.c_off) == (float(c[0]), float(c[1])):
            return
        self._running = edi.RunningDivisor(self.width, self.height, r.ts, r.te, r.f, c[0], c[1], mask=r.mask,
                                           event_counts=r.event_counts)

    def feed(self, events: np.ndarray) -> None:
        """The stream's next events (each once, in time order)."""
        if self._running is not None:
            self._running.feed(events)

    def take(self, events: np.ndarray, ts: int, te: int, f: int, c: tuple[float, float], mask: np.ndarray | None,
             event_counts: np.ndarray | None) -> edi.RunningDivisor | None:
        """At the deblur of [ts, te] with the batch `events` (every event from the exposure start on): the running
        integral, given the batch's events it had not seen, if it is exactly this deblur's; else None."""
        running, self._running = self._running, None
        if running is None:
            return None
        if not running.matches(ts, te, f, c[0], c[1], mask, event_counts):
            if not running.matches(ts, te, f, c[0], c[1], running.mask, event_counts):
                self.missed += 1
                return None
            running.remask(mask, events)  # only the mask changed (flicker or unreliable pixels flagged since)
            self.remasked += 1
        running.feed_from(events)
        self.used += 1
        return running

    def drop(self) -> None:
        """A gap or a jump in time: the running integral and the window history no longer hold."""
        self._running = None
        self._windows.clear()
