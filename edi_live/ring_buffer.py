"""The ring's storage: a fixed-capacity circular array of events addressed by global index.

Owns the memory and the wrap-around arithmetic only: event `i` (0, 1, 2, ... in push order) lives in slot
`i % capacity` until event `i + capacity` overwrites it. Which indices are still valid, who may write, and all
locking belong to `edi_live.ring.EventRing`, the only user.

Events are stored as raw int64 pairs (the 16-byte EVENT_DTYPE record: t, then x/y/p): a structured-dtype copy is
~20x slower in numpy, and the t column is a strided int64 view that np.searchsorted reads without a copy.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from edi_live.datatypes import EVENT_DTYPE, concat_events, empty_events


_PREFAULT_ROWS = 1 << 22  # events written per chunk at start-up (64 MiB)


def raw_pairs(events: np.ndarray) -> np.ndarray:
    """View EVENT_DTYPE events as (n, 2) int64 for fast copies (copied first only if not contiguous)."""
    return np.ascontiguousarray(events).view(np.int64).reshape(-1, 2)


def _events(raw: np.ndarray) -> np.ndarray:
    return raw.view(EVENT_DTYPE).reshape(-1)


class EventBuffer:
    """`capacity` events in a circle; every method takes global indices (not slots)."""

    def __init__(self, capacity: int, stop: Callable[[], bool] | None = None) -> None:
        """`stop`: asked between chunks of the start-up page touching; True ends it (a stop signal)."""
        self.capacity = int(capacity)
        # Written now (the kernel maps np.zeros' pages lazily): first-touch page faults cost ~4 µs per 4 kB page
        # on the development VM, i.e. up to 18 µs per 1000 events pushed while the first `capacity` events stream
        # in; this moves that cost to start-up, before data flows. In chunks, so that a stop signal is not held up
        # (16 GiB took 13 s); what a stop leaves unwritten is zeros all the same.
        self._buf = np.zeros((self.capacity, 2), dtype=np.int64)
        for start in range(0, self.capacity, _PREFAULT_ROWS):
            if stop is not None and stop():
                break
            self._buf[start:start + _PREFAULT_ROWS] = 0
        self._t = self._buf[:, 0]  # event times (strided view)

    def write(self, head: int, raw: np.ndarray) -> None:
        """Store `raw` ((n, 2) int64, n <= capacity) as the events head, head + 1, ..."""
        n = len(raw)
        start = head % self.capacity
        first = min(n, self.capacity - start)
        self._buf[start:start + first] = raw[:first]
        if first < n:
            self._buf[: n - first] = raw[first:]

    def copy_out(self, start: int, stop: int) -> np.ndarray:
        """A copy (EVENT_DTYPE) of the events start .. stop - 1 (stop - start <= capacity)."""
        if stop - start <= 0:
            return empty_events()
        cap = self.capacity
        a, b = start % cap, stop % cap
        if a < b:
            return _events(self._buf[a:b].copy())
        return concat_events((_events(self._buf[a:]), _events(self._buf[:b])))

    def t_at(self, index: int) -> int:
        return int(self._t[index % self.capacity])

    def search(self, start: int, stop: int, t_us: int) -> int:
        """First index in [start, stop) whose t >= t_us (stop if none); the events there must be sorted by t."""
        cap = self.capacity
        a, b = start % cap, stop % cap
        if a < b or stop - start == 0:
            return start + int(np.searchsorted(self._t[a:a + (stop - start)], t_us, side="left"))
        first = self._t[a:]
        i = int(np.searchsorted(first, t_us, side="left"))
        if i < len(first):
            return start + i
        return start + len(first) + int(np.searchsorted(self._t[:b], t_us, side="left"))
