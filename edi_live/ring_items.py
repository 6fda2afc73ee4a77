"""What the ring hands its consumer: chunks of events with their arrival times, and queued APS frames."""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from edi_live.datatypes import Frame


@dataclass(frozen=True, slots=True)
class EventChunk:
    """Events handed to the consumer (a copy), with the host arrival time of each push they came from.

    `push_ends[i]` is the end (exclusive, relative to this chunk) of the i-th push in it and `push_arrival_ns[i]`
    that push's arrival time. `gap` is True if data was lost right before or inside this chunk.
    """

    events: np.ndarray
    first_index: int
    push_ends: list[int]
    push_arrival_ns: list[int]
    gap: bool

    def arrival_ns_at(self, count: int) -> int:
        """Arrival time of the push holding event `count - 1` (the last of the first `count` events)."""
        if count <= 0 or not self.push_ends:
            return 0
        i = bisect.bisect_right(self.push_ends, count - 1)  # a few pushes per chunk: a list beats numpy here
        return self.push_arrival_ns[min(i, len(self.push_arrival_ns) - 1)]


@dataclass(frozen=True, slots=True)
class FrameEntry:
    """An APS frame in the queue. `end_index`: first event index after its exposure end."""

    frame: Frame
    end_index: int
    arrival_ns: int
    gap: bool = False
