"""`--mode nearest` bookkeeping for the worker: which latent times are held back until the next APS frame, and how
long they waited. Runs on the worker thread.

A time is held when it may be nearer the next APS frame than the current reference: past the midpoint predicted
from the last interval, less a tenth of the interval (frame intervals jitter), or any time after the reference
while no interval is known yet (the first frame, the first after a gap). The worker then splits the held times at
the true midpoint when the next frame arrives (`take_before`), so a held time never ends on the wrong side; only
a time released early (the next frame came more than a tenth of an interval early) can.
"""

from __future__ import annotations

import time

import numpy as np

_MAX_HELD = 4096  # beyond this, frames are rendered from the older reference rather than held
_MARGIN_DIV = 10  # hold from a tenth of the interval before the predicted midpoint


class NearestHoldBack:
    def __init__(self) -> None:
        self.held: list[tuple[int, int]] = []  # (t_us, arrival_ns) waiting for the next frame
        self.interval_us: int | None = None  # between the last two reference times
        self._waited_ms: list[float] = []
        self._after_gap = False

    def new_reference(self, previous_f_us: int | None, f_us: int) -> None:
        if previous_f_us is not None and f_us > previous_f_us and not self._after_gap:
            self.interval_us = f_us - previous_f_us
        self._after_gap = False

    def gap(self) -> None:
        """Data were lost: drop the held times; the interval across the gap says nothing about the next one."""
        self.held = []
        self.interval_us = None
        self._after_gap = True

    def should_hold(self, t_us: int, ref_f_us: int | None) -> bool:
        if ref_f_us is None or len(self.held) >= _MAX_HELD:
            return False
        if self.interval_us is None:
            return t_us > ref_f_us
        return t_us > ref_f_us + self.interval_us // 2 - self.interval_us // _MARGIN_DIV

    def take_before(self, mid_us: int | None) -> list[tuple[int, int]]:
        """The held times before `mid_us` (nearer the old reference), removed from the hold."""
        if mid_us is None or not self.held:
            return []
        early = [d for d in self.held if d[0] < mid_us]
        self.held = [d for d in self.held if d[0] >= mid_us]
        return early

    def take_all(self) -> list[tuple[int, int]]:
        taken, self.held = self.held, []
        return taken

    def waited(self, arrival_ns: int) -> None:
        """A held frame is rendered now: record how long after its last event's arrival."""
        self._waited_ms.append((time.monotonic_ns() - arrival_ns) / 1e6)
        if len(self._waited_ms) > 10_000:
            del self._waited_ms[:5_000]

    def waited_ms_p50(self) -> float | None:
        waited = list(self._waited_ms)
        return round(float(np.median(waited)), 3) if waited else None
