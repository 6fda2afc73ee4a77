"""Mains flicker: which pixels a lamp on AC power lights, so that the reconstructor trusts the APS frames there.

A lamp on 50 Hz mains flickers at 100 Hz (120 Hz on 60 Hz mains): a pixel it lights fires an ON burst and an OFF
burst every cycle. Over a cycle the light returns to where it was, but the events do not say so: on a real
DAVIS346 a lamp's halo fires ~8 ON and ~2 OFF events per cycle (aestream; OFF events are lost to the refractory
period and the pixel's bandwidth), so EDI's log image climbs by about c_on * 6 each cycle and the lamp blooms,
whatever c is. A third of aestream's events come from such pixels, and on the simulator a lamp drifts whenever
c_on/c_off are off.

`FlickerPixels` finds these pixels from the events alone, from the first frame on: a pixel whose OFF -> ON
switches come `cycles` times in a row at a mains period (7.3-11.3 ms, or twice that: a halo pixel misses
switches, and some lamps flicker at the mains frequency itself) is flagged, and stays flagged while such
cycles keep coming within `hold_us`. A flagged pixel's events are ignored like a hot pixel's: its latent value
goes back to the reference when it is flagged, and it shows what the APS frames say (each frame's value, which
the deblur takes as it is there). A moving edge crosses a pixel once and is never flagged; texture repeats at a
mains period only by chance, and briefly. A lamp that moves is shown where the latest APS frame saw it.

Between APS frames the flags found in a stream take effect at fixed points of the event clock (`steps`, `due`):
at the first event past the STEP_US span they were found in. Taking them at the end of each read made the
latent frames depend on where the reads were cut. The kernel stops at such a point, so a read without flag
changes (nearly all) is one call.

A scene without a lamp does not need the detector on every event (it was ~8 ns an event, about 7 % of the worker
on a busy scene). While no pixel is flagged, it reads only the first SCAN_US of every IDLE_PERIOD_US of the event
clock, counted from the first event it sees; once LAMP_PIXELS pixels are flagged (a lamp: hundreds to thousands of
pixels; a moving texture flags a few by chance) it reads every event until a scan ends with fewer. Pixels
flagged by a scan stay flagged until a later read shows their flicker stopped (up to one period after it did):
after a skipped range their hold counts from the scan's start plus two long cycles, so a small lamp that still
flickers is not released at its first event there. A lamp that comes into view is flagged within one idle period
plus its two cycles (at most ~0.45 s), and one in view from the start is flagged as before, in the first scan.
The points where it decides (a period's start, its scan's end) are fixed in the event clock, so the result does
not depend on how the events were cut into reads; a flag change due at the first event past its span is taken
there even if that event is not read.
"""

from __future__ import annotations

import numpy as np

import edi_live.edi as edi

STEP_US = 1_000  # flags found within one span of the event clock take effect at the first event after it
IDLE_PERIOD_US = 400_000  # with no pixel flagged, one scan per period...
SCAN_US = 80_000  # ...this long: three whole cycles even at 2 x 11.3 ms (a pixel that misses every other switch)
LAMP_PIXELS = 16  # flagged pixels from which a lamp is in view; a moving texture flags ~1-11 by chance


class FlickerPixels:
    def __init__(self, width: int, height: int, *, min_period_us: int = 7300, max_period_us: int = 11300,
                 cycles: int = 2, hold_us: int = 30_000, idle_scan: bool = True) -> None:
        self.width, self.height = width, height
        self._args = {"min_period_us": min_period_us, "max_period_us": max_period_us, "cycles": cycles,
                      "hold_us": hold_us}
        self._state = edi.FlickerState(width, height)
        self._changes = 0
        self._mask = np.zeros((height, width), bool)
        self._count = 0
        self._due: list[np.ndarray] = []  # pixels flagged by noted events, not yet taken
        self._due_changed = False
        self._due_span = 0
        self._idle_scan = idle_scan
        self._gate: tuple[int, int, int, bool] | None = None  # (period, phase start, phase end, read it)
        self._origin: int | None = None  # the event time the idle periods count from
        self._skipped = False  # a phase went unread since the last scan (flagged pixels' holds restart then)

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: the flagged pixels; replaced, never changed in place."""
        return self._mask

    @property
    def count(self) -> int:
        return self._count

    def observe(self, events: np.ndarray) -> tuple[bool, np.ndarray]:
        """Feed time-ordered events: (whether the mask changed, the flat pixels these events flagged)."""
        flagged = [edi.flicker_cycles(events[a:b], self._state, **self._args) for a, b in self._reads(events["t"])]
        flagged_now = flagged[0] if len(flagged) == 1 else np.concatenate(flagged or [np.empty(0, np.int64)])
        return self._refresh_mask(), flagged_now

    def steps(self, events: np.ndarray) -> list[tuple[int, np.ndarray | None, np.ndarray]]:
        """Feed time-ordered events; flag changes take effect at the first event past the STEP_US span they were
        found in. Returns those points among the events: (index, the mask from there on or None if unchanged, the
        flat pixels newly flagged); a span still open at the end is taken by a later call, or by due()."""
        t = events["t"]
        out: list[tuple[int, np.ndarray | None, np.ndarray]] = []
        done = 0
        for a, b in self._reads(t):
            self._due_in_skipped(t, done, a, out)
            out += [(a + at, mask, flagged) for at, mask, flagged in self._steps_within(events[a:b])]
            done = b
        self._due_in_skipped(t, done, int(t.size), out)
        return out

    def _due_in_skipped(self, t: np.ndarray, a: int, b: int, out: list) -> None:
        """A change found in a scan's last span is due at the first event past that span even when the detector
        does not read it (idle scans): there, not at the next range it reads (320 ms later)."""
        if self._due_changed and a < b:
            k = a + int(np.searchsorted(t[a:b], (self._due_span + 1) * STEP_US))
            if k < b:
                out.append((k, *self._take_due()))

    def _reads(self, t: np.ndarray):
        """The (start, end) index ranges of `t` the detector reads (module docstring), decided lazily: each range
        after the previous one has been read."""
        n = int(t.size)
        if not self._idle_scan or n == 0:
            return [(0, n)] if n else []
        if self._gate is not None and self._gate[1] <= int(t[0]) and int(t[-1]) < self._gate[2]:
            return [(0, n)] if self._gate[3] else []  # nearly every read: within one phase
        return self._reads_across(t)

    def _reads_across(self, t: np.ndarray):
        n, pos = int(t.size), 0
        while pos < n:
            ti = int(t[pos])
            if self._origin is None:
                self._origin = ti
            period = (ti - self._origin) // IDLE_PERIOD_US
            begin = self._origin + period * IDLE_PERIOD_US
            lo, hi = (begin, begin + SCAN_US) if ti < begin + SCAN_US else (begin + SCAN_US, begin + IDLE_PERIOD_US)
            if self._gate is None or self._gate[1] != lo:
                reads = lo == begin or int(np.count_nonzero(self._state.bits & 4)) >= LAMP_PIXELS
                self._gate = (period, lo, hi, reads)
                if not reads:
                    self._skipped = True
                elif self._skipped:
                    self._skipped = False
                    self._hold_from(lo)
            stop = pos + int(np.searchsorted(t[pos:], hi))
            if self._gate[3]:
                yield pos, stop
            pos = stop

    def _hold_from(self, t_us: int) -> None:
        """A scan after a skipped range: the flagged pixels' holds count from when each could show a whole cycle in
        it (its first switch within 2 * max_period_us, a cycle after it), not from its last cycle before the range:
        a lamp still flickering would be released at its first event and flagged again two cycles later."""
        flagged = (self._state.bits & 4) != 0
        if flagged.any():
            times = self._state.times[:, 1]
            times[flagged] = np.maximum(times[flagged], t_us + 2 * self._args["max_period_us"])

    def _steps_within(self, events: np.ndarray) -> list[tuple[int, np.ndarray | None, np.ndarray]]:
        out: list[tuple[int, np.ndarray | None, np.ndarray]] = []
        t, pos, n = events["t"], 0, len(events)
        if not self._due_changed:
            pos = self._read_until_change(events)
            if not self._due_changed:
                return out  # nearly every read: no flag changed, all read in one call
        while pos < n:
            if self._due_changed:
                # the events still in the span that changed belong to it; the change applies after them
                k = pos + int(np.searchsorted(t[pos:], (self._due_span + 1) * STEP_US))
                if k > pos:
                    self._read_until_change(events[pos:k])
                    pos = k
                if pos >= n:
                    break
                out.append((pos, *self._take_due()))
            pos += self._read_until_change(events[pos:])  # all of them, unless a flag changed
        return out

    def due(self) -> tuple[np.ndarray | None, np.ndarray] | None:
        """Now (e.g. at an APS frame): as a step of `steps`, from spans not yet taken; None if nothing is due."""
        return self._take_due() if self._due_changed else None

    def _read_until_change(self, events: np.ndarray) -> int:
        before = int(self._state.changes[0])
        flagged_now = edi.flicker_cycles(events, self._state, **self._args, span_us=STEP_US)
        read = int(self._state.read[0])
        if int(self._state.changes[0]) != before:
            self._due_changed = True
            self._due_span = int(events["t"][read - 1]) // STEP_US
        if flagged_now.size:
            self._due.append(flagged_now)
        return read

    def _take_due(self) -> tuple[np.ndarray | None, np.ndarray]:
        changed = self._refresh_mask()
        flagged = np.concatenate(self._due) if self._due else np.empty(0, np.int64)
        self._due, self._due_changed = [], False
        return (self._mask if changed else None), flagged

    def _refresh_mask(self) -> bool:
        """Whether flags changed since the mask was last made (it is replaced then, never changed in place)."""
        if int(self._state.changes[0]) == self._changes:
            return False
        self._changes = int(self._state.changes[0])
        self._mask = self._state.flagged.reshape(self.height, self.width)
        self._count = int(np.count_nonzero(self._mask))
        return True

    def reset(self) -> None:
        """Forget everything (a gap: the cycle timing no longer holds)."""
        self._state = edi.FlickerState(self.width, self.height)
        self._changes = 0
        self._mask = np.zeros((self.height, self.width), bool)
        self._count = 0
        self._due, self._due_changed = [], False
        self._gate, self._origin, self._skipped = None, None, False
