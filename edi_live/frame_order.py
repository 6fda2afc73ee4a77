"""Emitted frames put back in time order, for the outputs whose stream must not go back in time: the `--out` AEDAT4
file and the DV network stream (edi_live.writers, edi_live.dv_output).

In causal mode an APS frame's deblurred frame (t = its mid-exposure f) leaves after latent frames newer than f: the
latent frames keep coming from the previous reference while the new one is computed (with the deblur thread, and
more so in an unpaced run, more than 100 ms of sensor time was seen). `FrameOrder` holds the frames in a heap by
time and releases the oldest once no frame still to come can be older than it:

- its time is at most the newest reference time seen (references only move forward, so a later deblurred frame,
  at its own f, is newer) and at least `window_us` of sensor time behind the newest frame (with `widen`, the window
  widens to twice any disorder seen: a file's margin for the held frames of the nearest and fused modes);
- with `predict` (a live stream), or it is well before the next reference time expected from the spacing of the
  references (a quarter of that spacing ahead of it: exposures that change by up to half the frame interval keep
  their order), so that latent frames flow as they come and only those near the next keyframe wait for it; a
  keyframe that comes earlier than predicted after newer frames went out is late. The spacing is the smallest of
  the last few: a lost APS frame or a skipped deblur puts two references two periods apart, and predicting from
  that let the frames past the next keyframe out before it (too small a spacing only holds frames longer);
- or it has waited `hold_s` of wall time (a live stream's bound on the delay; None for a file, which waits as long
  as it must), or more than `max_held` frames wait (bounded memory).

A frame that comes older than one already released is late: counted, and left out. No threads, no I/O: the caller
owns the clock (`now_s`, e.g. time.monotonic()).
"""

from __future__ import annotations

import collections
import heapq

from edi_live.datatypes import Reconstruction

_NEVER = -(2**63)
_STEPS = 8  # reference spacings the prediction looks back on


class FrameOrder:
    """`add()` each emitted frame, then `ready()` for those that may go out now, in time order; `rest()` at the end."""

    def __init__(self, window_us: int, *, widen: bool = True, predict: bool = False, hold_s: float | None = None,
                 max_held: int = 2048) -> None:
        self.window_us, self.widen, self.hold_s, self.max_held = int(window_us), widen, hold_s, int(max_held)
        self.predict = predict
        self._ref_steps: collections.deque[int] = collections.deque(maxlen=_STEPS)  # spacings of the last references
        self._held: list[tuple[int, int, Reconstruction]] = []  # heap by (t, order of arrival)
        self._came: collections.deque[tuple[float, int]] = collections.deque()  # (wall time, order), as they came
        self._order = 0
        self._out: set[int] = set()  # orders released out of arrival order, not yet cleaned from _came
        self._newest_t = self._newest_ref_t = self.released_t = _NEVER
        self.late = 0  # frames that came older than one already released

    def __len__(self) -> int:
        return len(self._held)

    def add(self, rec: Reconstruction, now_s: float = 0.0) -> None:
        if self.widen and rec.t_us < self._newest_t:  # out of order: widen the window to what was seen
            self.window_us = max(self.window_us, 2 * (self._newest_t - rec.t_us))
        self._newest_t = max(self._newest_t, rec.t_us)
        ref = rec.t_us if rec.kind == "deblurred" else rec.ref_t_us
        if ref > self._newest_ref_t:
            if self._newest_ref_t != _NEVER:
                self._ref_steps.append(ref - self._newest_ref_t)
            self._newest_ref_t = ref
        heapq.heappush(self._held, (rec.t_us, self._order, rec))
        if self.hold_s is not None:
            self._came.append((now_s, self._order))
        self._order += 1

    def ready(self, now_s: float = 0.0) -> list[Reconstruction]:
        """The frames that may go out now, oldest first (late ones left out and counted)."""
        out: list[Reconstruction] = []
        while self._held and (self._safe(self._held[0][0]) or len(self._held) > self.max_held
                              or self._waited_out(now_s)):
            self._release(heapq.heappop(self._held), out)
        return out

    def rest(self) -> list[Reconstruction]:
        """Every frame still held, oldest first (the stream ends)."""
        out: list[Reconstruction] = []
        while self._held:
            self._release(heapq.heappop(self._held), out)
        return out

    def next_due_s(self) -> float | None:
        """The wall time at which the frame held longest has waited hold_s (None: nothing waits on the clock)."""
        self._clean_came()
        return self._came[0][0] + self.hold_s if self._came and self.hold_s is not None else None

    def _safe(self, t: int) -> bool:
        if t < self._newest_t - self.window_us and t <= self._newest_ref_t:
            return True
        step = min(self._ref_steps, default=0)
        return self.predict and step > 0 and t < self._newest_ref_t + step - step // 4

    def _waited_out(self, now_s: float) -> bool:
        due = self.next_due_s()
        return due is not None and now_s >= due

    def _release(self, item: tuple[int, int, Reconstruction], out: list[Reconstruction]) -> None:
        t, order, rec = item
        if self.hold_s is not None:
            self._out.add(order)
        if t < self.released_t:
            self.late += 1
            return
        self.released_t = t
        out.append(rec)

    def _clean_came(self) -> None:
        while self._came and self._came[0][1] in self._out:
            self._out.discard(self._came.popleft()[1])
