"""Pacing: maps sensor time (µs) to host `time.monotonic()` with a speed factor, for the replay (drivers/replay.py)
and the USB emulator's device time (drivers/emulator.py).

speed 1 replays in real time, 4 four times faster, 0 as fast as possible. The schedule is anchored once (the first
timestamp meets the first call), so waiting never accumulates drift. A jump of the recording's clock by more than
MAX_GAP_US (a clock reset: minutes to years between two packets) is not waited out: the schedule moves past it,
with one warning. Falling more than MAX_LATE_S behind the schedule (the process was suspended with Ctrl-Z, the
machine stalled) is not caught up by replaying the backlog at full speed: the schedule restarts at the late
timestamp, with one warning, as a paused video resumes where it stopped. A replay slower than its speed asks for
(an overloaded node) is re-anchored the same way each time it falls that far behind, so it runs as fast as it can,
as it did before.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

log = logging.getLogger(__name__)

MAX_GAP_US = 60_000_000
"""Longest pause between two timestamps that is replayed as a pause; a longer one is a jump of the clock."""

JUMPS_SHOWN = 3
"""Clock jumps warned about; later ones (a looped recording repeats its own every pass) are logged at debug level."""

MAX_LATE_S = 1.0
"""How far (host seconds) data may fall behind its schedule and still be caught up; later, pacing restarts."""


class Pacer:
    """Decides when data stamped `t_us` is due on the host clock."""

    def __init__(self, speed: float = 1.0, clock: Callable[[], float] = time.monotonic, name: str = "replay") -> None:
        if not speed >= 0:  # also rejects NaN
            raise ValueError(f"speed must be >= 0 (got {speed})")
        self.speed = float(speed)
        self._clock = clock
        self._name = name  # what is paced, in the warnings
        self._anchor_t_us: int | None = None
        self._anchor_s = 0.0
        self._latest_t_us: int | None = None
        self._late_warned = False
        self._jumps = 0
        self._first_t_us: int | None = None
        self._jumped_us = 0  # clock jumps moved past: not replayed time

    @property
    def unpaced(self) -> bool:
        return self.speed == 0

    def anchor(self, t_us: int) -> None:
        """Make sensor time `t_us` correspond to now (done automatically on the first `delay_s`)."""
        self._anchor_t_us, self._anchor_s = int(t_us), self._clock()
        self._latest_t_us = int(t_us)

    def delay_s(self, t_us: int) -> float:
        """Seconds from now until `t_us` is due (<= 0: due already)."""
        if self.unpaced:
            return 0.0
        if self._anchor_t_us is None:
            self.anchor(t_us)
            self._first_t_us = int(t_us)
        elif int(t_us) - self._latest_t_us > MAX_GAP_US:  # due when the latest timestamp was, not years later
            gap = int(t_us) - self._latest_t_us
            self._anchor_t_us += gap
            self._jumped_us += gap
            self._jumps += 1  # with --loop the same jump comes back every pass: the first few are shown
            (log.warning if self._jumps <= JUMPS_SHOWN else log.debug)(
                "the recording's clock jumps %s ahead at %d µs: replayed without waiting for it%s", _span(gap),
                self._latest_t_us, " (further jumps are not shown)" if self._jumps == JUMPS_SHOWN else "")
        self._latest_t_us = int(t_us) if self._latest_t_us is None else max(self._latest_t_us, int(t_us))
        due = self._anchor_s + (int(t_us) - self._anchor_t_us) / (1e6 * self.speed)
        delay = due - self._clock()
        if delay < -MAX_LATE_S:
            self.anchor(t_us)
            (log.debug if self._late_warned else log.warning)(
                "paced %s resumed %.1f s behind its schedule, %.1f s into the %s (the process was stopped, or could "
                "not keep up): it goes on from there at its speed instead of rushing through the backlog",
                self._name, -delay, _replayed_s(t_us, self._first_t_us, self._jumped_us), self._name)
            self._late_warned = True
            return 0.0
        return delay

    def wait(self, t_us: int, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Sleep until `t_us` is due, at most `timeout_s`. True when due; False on timeout or when `stop` is set."""
        delay = self.delay_s(t_us)
        if delay <= 0:
            return True
        if stop is not None:
            return not stop.wait(min(delay, timeout_s)) and delay <= timeout_s
        time.sleep(min(delay, timeout_s))
        return delay <= timeout_s


def _replayed_s(t_us: int, first_t_us: int | None, jumped_us: int) -> float:
    """Sensor seconds replayed up to t_us: from the first timestamp paced (across --loop's passes, whose time runs
    on), without the clock jumps moved past."""
    return (int(t_us) - (int(t_us) if first_t_us is None else first_t_us) - jumped_us) / 1e6


def _span(us: int) -> str:
    seconds = us / 1e6
    for unit, size in (("years", 365 * 86400), ("days", 86400), ("hours", 3600), ("minutes", 60)):
        if seconds >= size:
            return f"{seconds / size:.1f} {unit}"
    return f"{seconds:.1f} s"
