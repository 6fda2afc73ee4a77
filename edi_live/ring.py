"""The bounded hand-over between the pump thread (one producer) and the EDI worker (one consumer).

`EventRing` holds a preallocated ring of events (EVENT_DTYPE) and a bounded queue of APS frames. Every event gets
a global index (0, 1, 2, ... in push order, which is time order). The consumer reads events in order through a
cursor (`read_events`) and takes a frame once its cursor reaches the frame's `end_index`: the index just past the
last event with t <= exposure_end_us, so every event of the exposure has been read by then::

    index:   ... old (history, already read) ... | read cursor ... unread ... | head (next write)
             <------- at least capacity/2 -------><----- at most capacity/2 ---->

Half the capacity is reserved for already-read history, so `window(t0_us, t1_us)` can still cut an APS frame's
exposure [t0, t1) out of the ring (half-open, by np.searchsorted) after the worker has streamed through it.

Overflow policy (the only place live and replay differ):
- "drop_oldest" (live): push never blocks. When unread events would exceed capacity/2, the oldest unread ones
  are skipped; they are counted in `dropped_events` and the next read is flagged `gap=True`.
- "wait" (replay): push waits for the consumer, so nothing is lost at any replay speed.

All state is guarded by one condition variable (`_cond`). Copies in and out happen under its lock, so a live
overwrite can never change data under the worker: windows and reads are copies, never views. The consumer may
wait with a `WakeWhen` (edi_live.ring_wake): then pushes that do not meet it do not wake it.
The storage itself (a circular array addressed by global index) is `edi_live.ring_buffer.EventBuffer`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Callable

import numpy as np

from edi_live.datatypes import Frame, Packet, as_events, empty_events
from edi_live.ring_buffer import EventBuffer, raw_pairs
from edi_live.ring_items import EventChunk, FrameEntry
from edi_live.ring_wake import WakeWhen

POLICIES = ("drop_oldest", "wait")
log = logging.getLogger(__name__)


class EventRing:
    """Bounded single-producer / single-consumer ring of events plus a bounded APS frame queue."""

    def __init__(self, capacity_events: int = 1 << 22, capacity_frames: int = 16, policy: str = "wait",
                 stop: Callable[[], bool] | None = None) -> None:
        if policy not in POLICIES:
            raise ValueError(f"policy must be one of {POLICIES} (got {policy!r})")
        if capacity_events < 16 or capacity_frames < 1:
            raise ValueError(f"ring capacity too small (got {capacity_events} events, {capacity_frames} frames)")
        self.capacity_events = int(capacity_events)
        self.capacity_frames = int(capacity_frames)
        self.policy = policy
        self.max_unread = self.capacity_events // 2
        self._store = EventBuffer(self.capacity_events, stop)  # stop(): a stop signal ends its memory touching
        # The producer thread (push) and the consumer thread (read_events/pop_frame/window/wait) meet here.
        self._cond = threading.Condition()
        self._head = 0
        self._read = 0
        self._pushes: deque[tuple[int, int]] = deque()  # (end index, arrival_ns), unread pushes only
        self._gaps: deque[int] = deque()  # indices before which data was lost
        self._frames: deque[FrameEntry] = deque()
        self._closed = False
        self._version = 0  # bumped on every push and on close: "data advanced"
        # the consumer while it waits: (version it saw, its WakeWhen or None); pushes that do not meet the
        # condition do not wake it (edi_live.ring_wake)
        self._waiting: tuple[int, WakeWhen | None] | None = None
        self._poked = False  # a poke() the consumer's next wait() has not seen: that wait returns at once
        self._idle_waiters = 0  # producers in wait_consumer_idle
        # What a producer blocked by the wait policy waits for (0 / False: it is not waiting). The consumer
        # notifies only when that much room is free: a wake-up costs a futex syscall plus a GIL hand-over (14 %
        # of the worker's GIL time when every read woke the pump), and refilling in large steps needs few.
        self._producer_wants = 0
        self._producer_wants_frame = False
        self._refill = max(1, self.max_unread // 8)
        self.watermark_us = -(2**63)
        self.pushed_events = 0
        self.pushed_frames = 0
        self.dropped_events = 0
        self.dropped_frames = 0
        self.gap_count = 0
        self.history_truncated = 0  # windows that reached back past the retained history
        self.producer_wait_s = 0.0

    # ---------------------------------------------------------------- producer side (pump thread)

    def push(self, packet: Packet, timeout_s: float | None = None) -> bool:
        """Append a packet's events and frames. Returns False if the ring was closed, or if the wait policy
        could not make room within `timeout_s` (the part already written stays)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        arrival = packet.arrival_ns or time.monotonic_ns()
        events = as_events(packet.events)
        if packet.gap:
            self._mark_gap_at_head()
        frames = sorted(packet.frames, key=lambda f: f.exposure_end_us)
        cut = 0
        for frame in frames:
            end = int(np.searchsorted(events["t"], frame.exposure_end_us, side="right")) if len(events) else 0
            end = max(end, cut)
            if not self._write(events[cut:end], arrival, deadline):
                return False
            cut = end
            if not self._put_frame(frame, arrival, deadline):
                return False
        if not self._write(events[cut:], arrival, deadline):
            return False
        with self._cond:
            if packet.watermark_us > self.watermark_us:
                self.watermark_us = int(packet.watermark_us)
                self._version += 1
                self._notify_consumer()
        return True

    def _mark_gap_at_head(self) -> None:
        with self._cond:
            self._gaps.append(self._head)
            self.gap_count += 1

    def _wait_for_room(self, needed: int, deadline: float | None) -> bool:
        """Wait policy: block until `needed` more unread items fit. Caller holds the lock."""
        start = time.monotonic()
        try:
            while not self._closed and self._head - self._read + needed > self.max_unread:
                remaining = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
                if remaining <= 0:
                    return False
                self._producer_wants = needed
                self._cond.wait(remaining)
            return not self._closed
        finally:
            self._producer_wants = 0
            self.producer_wait_s += time.monotonic() - start

    def _write(self, events: np.ndarray, arrival_ns: int, deadline: float | None) -> bool:
        n_total = len(events)
        if n_total == 0:
            return not self._closed
        raw = raw_pairs(events)
        done = 0
        if self.policy == "drop_oldest" and n_total > self.max_unread:
            # A burst larger than the ring: keep its newest part, count the rest.
            skipped = n_total - self.max_unread
            with self._cond:
                self.dropped_events += skipped
                self._gaps.append(self._head)
                self.gap_count += 1
            done = skipped
        while done < n_total:
            with self._cond:
                if self._closed:
                    return False
                if self.policy == "wait":
                    free = self.max_unread - (self._head - self._read)
                    if free <= 0:  # full: wait until a good part of it is free again (few wake-ups)
                        if not self._wait_for_room(min(n_total - done, self._refill), deadline):
                            return False
                        continue
                    n = min(n_total - done, free)
                else:
                    n = min(n_total - done, self.max_unread)
                    overflow = self._head - self._read + n - self.max_unread
                    if overflow > 0:
                        self._drop_unread(overflow)
                self._store.write(self._head, raw[done:done + n])
                self._pushes.append((self._head + n, arrival_ns))
                self._head += n
                self.pushed_events += n
                last_t = int(raw[done + n - 1, 0])
                if last_t > self.watermark_us:
                    self.watermark_us = last_t
                self._version += 1
                self._notify_consumer()
            done += n
        return True

    def _notify_consumer(self, always: bool = False) -> None:
        """Wake the consumer unless it waits with a WakeWhen this push does not meet (lock held); a woken one no
        longer counts as waiting. A producer blocked for room is woken only by the consumer (read_events)."""
        waiting = self._waiting
        if always or waiting is None or self._due(waiting[1]):
            self._waiting = None
            self._cond.notify_all()

    def _due(self, wake: WakeWhen | None) -> bool:
        """Whether a consumer waiting with `wake` has something to do: its condition met, a frame queued that it has
        not seen (with `frame_late_us`, once the watermark is past that frame's late events), closed."""
        if wake is None or self._closed or wake.met(self._head, self.watermark_us):
            return True
        return len(self._frames) > wake.frames and (
            wake.frame_late_us is None
            or self.watermark_us > self._frames[wake.frames].frame.exposure_end_us + wake.frame_late_us)

    def _drop_unread(self, count: int) -> None:
        """drop_oldest: skip the `count` oldest unread events (lock held)."""
        self._read += count
        self.dropped_events += count
        self.gap_count += 1
        self._gaps.append(self._read)
        while self._pushes and self._pushes[0][0] <= self._read:
            self._pushes.popleft()

    def _put_frame(self, frame: Frame, arrival_ns: int, deadline: float | None) -> bool:
        with self._cond:
            if self.policy == "wait":
                start = time.monotonic()
                while not self._closed and len(self._frames) >= self.capacity_frames:
                    remaining = 0.1 if deadline is None else min(0.1, deadline - time.monotonic())
                    if remaining <= 0:
                        self._producer_wants_frame = False
                        self.producer_wait_s += time.monotonic() - start
                        return False
                    self._producer_wants_frame = True
                    self._cond.wait(remaining)
                self._producer_wants_frame = False
                self.producer_wait_s += time.monotonic() - start
            if self._closed:
                return False
            gap = False
            if len(self._frames) >= self.capacity_frames:
                self._frames.popleft()
                self.dropped_frames += 1
                gap = True
            self._frames.append(FrameEntry(frame, self._head, arrival_ns, gap))
            self.pushed_frames += 1
            self._version += 1
            self._notify_consumer()  # at once, unless it waits for the frame's late events (WakeWhen.frame_late_us)
        return True

    def close(self) -> None:
        """End of input: the consumer drains what is left, then sees `exhausted`. Idempotent, any thread."""
        with self._cond:
            self._closed = True
            self._version += 1
            self._notify_consumer(always=True)

    def poke(self) -> None:
        """Wake a consumer blocked in wait() (e.g. a helper thread finished work for it). Any thread."""
        with self._cond:
            self._version += 1
            self._poked = True  # also when it comes before the consumer's wait(): that wait must not block
            self._notify_consumer(always=True)

    # ---------------------------------------------------------------- consumer side (worker thread)

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def exhausted(self) -> bool:
        """Closed and everything read."""
        with self._cond:
            return self._closed and self._head == self._read and not self._frames

    @property
    def head(self) -> int:
        return self._head

    @property
    def read_index(self) -> int:
        return self._read

    @property
    def version(self) -> int:
        return self._version

    def wait(self, since_version: int, timeout_s: float, wake: WakeWhen | None = None) -> bool:
        """Block until data advanced past `since_version` (or close), at most `timeout_s`. True if it did.
        With `wake`, data that does not meet it (edi_live.ring_wake) does not end the wait; a poke() does, also one
        that came after the consumer read `since_version` but before it called wait()."""
        with self._cond:
            poked, self._poked = self._poked, False
            if self._version != since_version and (poked or self._due(wake)):
                return True
            self._waiting = (since_version, wake)
            if self._idle_waiters:
                self._cond.notify_all()
            try:
                self._cond.wait(timeout_s)
            finally:
                self._waiting = None
                self._poked = False  # a poke during the wait ended it
            return self._version != since_version

    def wait_consumer_idle(self, timeout_s: float) -> bool:
        """Producer side: block until the consumer waits for data that has not come, i.e. it has done all it
        will do with what was pushed so far (a lockstep replay in sensor time, for tests and benchmarks).
        False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            self._idle_waiters += 1
            try:
                while not self._consumer_idle():
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return False
                    self._cond.wait(remaining)
                return True
            finally:
                self._idle_waiters -= 1

    def _consumer_idle(self) -> bool:
        waiting = self._waiting
        return waiting is not None and (self._version == waiting[0] or not self._due(waiting[1]))

    def read_events(self, max_n: int, until_index: int | None = None, through_t_us: int | None = None) -> EventChunk:
        """Take up to `max_n` unread events (not past `until_index`, nor past the first event later than
        `through_t_us`, nor past a queued frame's `end_index`, also one at the cursor unless `through_t_us` is
        given) as a copy and advance the cursor. With `through_t_us` the first queued frame does not stop it
        either: that is the consumer's, held until its late events are in. The frame bound is checked under the
        lock: a frame pushed after the consumer's peek_frame() still stops the read at its exposure end, so where
        reads stop depends on the stream, not on when the producer ran."""
        with self._cond:
            start = self._read
            stop = self._head if until_index is None else min(self._head, until_index)
            for k, entry in enumerate(self._frames):
                # a frame at the cursor stops a plain read too (it was queued after the consumer's look); a read
                # through a time is the consumer's for the first frame (its late window), so it goes on
                if through_t_us is not None and k == 0:
                    continue
                if entry.end_index > start or (entry.end_index == start and through_t_us is None):
                    stop = min(stop, entry.end_index)
                    break
            if through_t_us is not None and stop > start:
                # the first queued frame's own events are read however late it was queued (a live camera sends a
                # frame after its readout, behind events later than its late window: one event per read then)
                floor = self._frames[0].end_index if self._frames else start
                stop = min(stop, max(floor, self._store.search(start, stop, through_t_us + 1) + 1))
            n = max(0, min(max_n, stop - start))
            if n == 0:
                return EventChunk(empty_events(), start, [], [], False)
            events = self._store.copy_out(start, start + n)
            ends, arrivals = [], []
            for end, arrival in self._pushes:
                ends.append(min(end, start + n) - start)
                arrivals.append(arrival)
                if end >= start + n:
                    break
            while self._pushes and self._pushes[0][0] <= start + n:
                self._pushes.popleft()
            gap = False
            while self._gaps and self._gaps[0] < start + n:  # data was lost before one of these events
                gap = True
                self._gaps.popleft()
            self._read = start + n
            self._version += 1
            wants = self._producer_wants
            if wants and self._head - self._read + wants <= self.max_unread:
                self._cond.notify_all()  # the waiting producer has the room it waits for
        return EventChunk(events, start, ends, arrivals, gap)

    def peek_frame(self) -> FrameEntry | None:
        with self._cond:
            return self._frames[0] if self._frames else None

    def pop_frame(self) -> FrameEntry | None:
        with self._cond:
            if not self._frames:
                return None
            entry = self._frames.popleft()
            self._version += 1
            if self._producer_wants_frame:
                self._cond.notify_all()
            return entry

    def window(self, t0_us: int, t1_us: int, end_index: int | None = None) -> np.ndarray:
        """A copy of the retained events with t0_us <= t < t1_us among indices < end_index (default: the read
        cursor). Events older than the retained history are gone; that is counted in `history_truncated`."""
        with self._cond:
            stop = self._read if end_index is None else min(end_index, self._head)
            oldest = max(0, self._head - self.capacity_events)
            if stop <= oldest:
                return empty_events()
            lo = self._store.search(oldest, stop, t0_us)
            hi = self._store.search(oldest, stop, t1_us)
            if lo == oldest and oldest > 0 and self._store.t_at(oldest) > t0_us:
                self.history_truncated += 1
                if self.history_truncated == 1:  # said once; the summary gives the count
                    log.warning("the ring's history (half of --ring-events: %d events) no longer holds the start of an "
                                "APS frame's exposure: it is deblurred from part of its events; raise --ring-events",
                                self.capacity_events // 2)
            return self._store.copy_out(lo, max(lo, hi))

    # ---------------------------------------------------------------- any thread

    @property
    def unread_events(self) -> int:
        return self._head - self._read

    @property
    def occupancy(self) -> float:
        """Unread events as a fraction of what may be unread (1.0 = full: waiting or dropping)."""
        return (self._head - self._read) / self.max_unread

    def stats(self) -> dict:
        return {"ring_occupancy": round(self.occupancy, 4), "ring_unread_events": self.unread_events,
                "ring_frames_queued": len(self._frames), "ring_dropped_events": self.dropped_events,
                "ring_dropped_frames": self.dropped_frames, "ring_gaps": self.gap_count,
                "ring_history_truncated": self.history_truncated,
                "ring_producer_wait_s": round(self.producer_wait_s, 3)}
