"""When an APS frame may be deblurred: once every event of its exposure window, in the event clock, has been read.

The ring queues a frame at the index just past its stated exposure end. When events arrive `offset` µs late
against the APS exposure (a real DAVIS: pixel latency), its window in the event clock ends at te + offset, so the
worker reads on until an event later than that, or the input ends, or no event came for a while (then none will).
Runs on the worker thread.
"""

from __future__ import annotations

import dataclasses
import time

from edi_live.datatypes import Frame

QUIET_S = 1.0  # no event for this long while waiting: the window is as complete as it will get


class FrameGate:
    def __init__(self) -> None:
        self.t_read = -(2**63)  # time of the last event read from the ring
        self._waiting_since: float | None = None
        self.held_through: int | None = None  # the frame last asked about waits for an event later than this

    def events_read(self, t_last_us: int) -> None:
        self.t_read = t_last_us
        self._waiting_since = None

    def ready(self, frame: Frame, offset_us: int, input_done: bool) -> bool:
        """`input_done`: no event will come any more (input closed and every event read)."""
        self.held_through = None
        if offset_us <= 0 or input_done or self.t_read > frame.exposure_end_us + offset_us:
            return True
        now = time.monotonic()
        if self._waiting_since is None:
            self._waiting_since = now
        if now - self._waiting_since > QUIET_S:
            self._waiting_since = None
            return True
        self.held_through = frame.exposure_end_us + offset_us
        return False


def in_event_clock(frame: Frame, offset_us: int) -> Frame:
    """The frame with its exposure window moved into the event clock (events `offset_us` late)."""
    if not offset_us:
        return frame
    return dataclasses.replace(frame, exposure_start_us=frame.exposure_start_us + offset_us,
                               exposure_end_us=frame.exposure_end_us + offset_us)
