"""The DV network input's queue between its reader threads (one per connection) and the consumer.

Owns the bound and what goes when it is reached: the oldest event packets first (over `max_events` events or
`max_items` items), counted in the source's `dropped_events`; frames, IMU and trigger packets over
`max_other_bytes`, oldest first, with a warning at the first drop and their count in `report_drops()`. Every drop
marks a gap, handed to the next packet yielded (`take_gap()`). Items are (type identifier, data, arrival ns) or
("fault", SourceError); faults are never dropped.
"""

from __future__ import annotations

import collections
import logging
import threading

from edi_live.aedat4.header import STREAM_NAMES
from edi_live.datatypes import SourceStatus

log = logging.getLogger("drivers.dv_network")


def _nbytes(item: tuple) -> int:
    """The memory a queued frame, IMU or trigger item holds."""
    return item[1].image.nbytes if item[0] == "FRME" else item[1].nbytes


class DvQueue:
    """Bounded, thread-safe; `put()` from the readers, `get()` from the consumer (see module doc)."""

    def __init__(self, status: SourceStatus, max_events: int, max_items: int, max_other_bytes: int) -> None:
        self.status = status
        self.max_events, self.max_items, self.max_other_bytes = max_events, max_items, max_other_bytes
        self.cv = threading.Condition()
        self.items: collections.deque = collections.deque()
        self.queued_events = 0
        self._other_bytes = 0  # frames, IMU and triggers queued
        self._dropped_other: collections.Counter = collections.Counter()  # of those, dropped: type -> count
        self._gap = False

    def __len__(self) -> int:
        return len(self.items)

    def put(self, item: tuple) -> None:
        with self.cv:
            if item[0] == "EVTS":
                self.queued_events += len(item[1])
            elif item[0] != "fault":
                self._other_bytes += _nbytes(item)
            self.items.append(item)
            while (self.queued_events > self.max_events or len(self.items) > self.max_items) and self._drop_events():
                pass
            # events alone are dropped above; frames, IMU and triggers from a server sending them faster than
            # they are taken would otherwise queue without bound
            while self._other_bytes > self.max_other_bytes and self._drop_other(item):
                pass
            self.cv.notify()

    def get(self, timeout_s: float, stopped: threading.Event) -> tuple | None:
        with self.cv:
            if not self.items and not stopped.is_set():
                self.cv.wait(timeout_s)
            if not self.items:
                return None
            item = self.items.popleft()
            if item[0] == "EVTS":
                self.queued_events -= len(item[1])
            elif item[0] != "fault":
                self._other_bytes -= _nbytes(item)
            return item

    def wake(self) -> None:
        with self.cv:
            self.cv.notify_all()

    def mark_gap(self) -> None:
        with self.cv:  # (re-entrant: the drops below call it with the lock held)
            self.status.gaps += not self._gap
            self._gap = True

    def take_gap(self) -> bool:
        """Whether anything was lost since the last call."""
        with self.cv:
            gap, self._gap = self._gap, False
            return gap

    def report_drops(self) -> None:
        """One warning line with the frames, IMU and trigger packets dropped so far (once)."""
        with self.cv:
            dropped, self._dropped_other = self._dropped_other, collections.Counter()
        if dropped:
            log.warning("the DV input dropped %s that arrived faster than edi-live took them",
                        ", ".join(f"{n} {'frames' if t == 'FRME' else STREAM_NAMES[t] + ' packets'}"
                                  for t, n in sorted(dropped.items())))

    def _drop_events(self) -> bool:
        """Drop the oldest queued event packet (faults, frames and IMU are kept); False when there is none."""
        for i, queued in enumerate(self.items):
            if queued[0] == "EVTS":
                del self.items[i]
                self.queued_events -= len(queued[1])
                self.status.dropped_events += len(queued[1])
                self.mark_gap()
                return True
        return False

    def _drop_other(self, newest: tuple) -> bool:
        """Drop the oldest queued frame, IMU or trigger packet other than `newest`; False when there is none."""
        for i, queued in enumerate(self.items):
            if queued[0] not in ("EVTS", "fault") and queued is not newest:
                del self.items[i]
                self._other_bytes -= _nbytes(queued)
                if not self._dropped_other:
                    log.warning("the DV %s arrive faster than edi-live takes them: the oldest are dropped "
                                "(counted when the input closes)", STREAM_NAMES[queued[0]])
                self._dropped_other[queued[0]] += 1
                self.mark_gap()
                return True
        return False
