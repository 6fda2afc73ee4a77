"""When the streaming worker cuts a latent frame: every `every` events, or at the first event `every_us` of sensor
time after the previous latent frame, whichever comes first.

Counting events alone gives a slow scene a slow video: at 40k events/s and the default 1000 events a frame, a
frame every 25 ms, fewer than the APS frames. The time rule bounds how stale the shown image gets while the scene
moves (none come, nothing changes: the heartbeat covers that). Both rules follow the event stream only (sensor
time, counts), never the host clock, so a replay cuts the same frames however its reads are split. The caller
says which events the time rule may cut at (`timed`): the worker turns it off where the activity test only
holds the scene active after motion, which is mostly noise.

Plain functions, one compiled pass for reads where the time rule cuts, and one small state object the worker
thread owns; no threads, no I/O.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numba import njit

_NEVER = np.iinfo(np.int64).max
_VECTOR_CUTS = 256  # up to this many count cuts in a read, numpy checks that no time cut comes first; past it (a
# small --every), the compiled pass over the events is cheaper than those checks (~1 ns an event)


def frame_cadence_us(every_ms: float) -> int:
    """--every-ms in whole µs (the event clock's unit): 0 stays 0 (off), anything above it is at least 1 µs."""
    return max(1, round(every_ms * 1000)) if every_ms > 0 else 0


class FrameCadence:
    """The time rule's clock: the sensor time of the latest latent frame (`made`; a deblurred frame shows its
    mid-exposure, so it does not restart the clock). `every_us` 0: events only."""

    def __init__(self, every: int, every_us: int) -> None:
        if every < 1 or every_us < 0:
            raise ValueError(f"a frame cadence needs every >= 1 and every_us >= 0 (got {every}, {every_us})")
        self.every, self.every_us = int(every), int(every_us)
        self.last_t = -_NEVER  # no frame yet: the time rule waits for the first one

    def made(self, t_us: int) -> None:
        """A frame at sensor time t_us (a latent frame's last event)."""
        self.last_t = max(self.last_t, int(t_us))

    def _due_t(self, timed: bool = True) -> int:
        return _NEVER if not (timed and self.every_us) or self.last_t == -_NEVER else self.last_t + self.every_us

    def cuts(self, t: np.ndarray, since: int, timed: bool = True) -> tuple[Sequence[int], int]:
        """(end index of each frame's last event in `t`, events left after the last one): for events in time
        order following `since` events that made no frame yet; `timed` False: by count only. Moves the clock to
        the last cut."""
        n, every = int(t.size), self.every
        counted = range(max(1, every - since), n + 1, every)
        out: Sequence[int] = counted
        if n and self._time_may_cut(t, counted, timed):  # one compiled pass
            ends = np.empty(n, np.int64)
            out = ends[:_walk(t, since, every, self.every_us, self.last_t != -_NEVER, self.last_t, ends)]
        if len(out):
            self.made(int(t[out[-1] - 1]))
            return out, n - int(out[-1])
        return out, since + n

    def _time_may_cut(self, t: np.ndarray, counted: range, timed: bool) -> bool:
        """Whether the time rule may cut somewhere in `t` (non-empty), where `counted` are the count rule's cuts."""
        if not (timed and self.every_us):
            return False
        if self.last_t == -_NEVER:  # the first count cut starts the rule
            return len(counted) > 0
        due = self.last_t + self.every_us  # later frames fall due later still: a read ending before it has none
        return not (int(t[-1]) < due or len(counted) <= _VECTOR_CUTS and _count_rule_wins(t, counted, due,
                                                                                              self.every_us))

    def take(self, t: np.ndarray, since: int, timed: bool = True) -> int:
        """How many of `t` (time order) to take before the next frame is due by either rule (all when none is);
        the caller cuts a frame when the count reaches `every` or the last event taken is past the time rule."""
        by_count = max(1, self.every - since)
        due = self._due_t(timed)
        if due == _NEVER or t.size == 0 or int(t[min(by_count, t.size) - 1]) < due:
            return min(by_count, int(t.size))
        return int(np.searchsorted(t, due, "left")) + 1

    def due(self, t_us: int) -> bool:
        """Whether an event at t_us makes a frame by the time rule."""
        return t_us >= self._due_t()


def _count_rule_wins(t: np.ndarray, counted: range, due: int, every_us: int) -> bool:
    """Whether no event reaches the time rule before the count rule cuts (the common case on a busy scene): each
    counted frame's last event comes before its time rule's due time, and the events after the last cut too."""
    if not len(counted):
        return int(t[-1]) < due
    last = t[np.arange(counted.start, counted.stop, counted.step, dtype=np.int64) - 1]  # each cut's last event
    dues = np.concatenate(([due], last[:-1] + every_us))  # the time rule's due time for each of those frames
    return bool(np.all(last < dues)) and int(t[-1]) < int(last[-1]) + every_us


@njit(cache=True, nogil=True)
def _walk(t, since, every, every_us, has_last, last_t, ends):  # noqa: ANN001
    """Both rules event by event: the end index of each frame into `ends`; returns how many."""
    k = 0
    for i in range(t.size):
        since += 1
        if since >= every or (has_last and t[i] >= last_t + every_us):
            ends[k] = i + 1
            k += 1
            since = 0
            last_t = t[i]
            has_last = True  # (called with every_us > 0 only)
    return k
