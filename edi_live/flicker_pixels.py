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
"""

from __future__ import annotations

import numpy as np

import edi_live.edi as edi

STEP_US = 1_000  # flags found within one span of the event clock take effect at the first event after it


class FlickerPixels:
    def __init__(self, width: int, height: int, *, min_period_us: int = 7300, max_period_us: int = 11300,
                 cycles: int = 2, hold_us: int = 30_000) -> None:
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

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: the flagged pixels; replaced, never changed in place."""
        return self._mask

    @property
    def count(self) -> int:
        return self._count

    def observe(self, events: np.ndarray) -> tuple[bool, np.ndarray]:
        """Feed time-ordered events: (whether the mask changed, the flat pixels these events flagged)."""
        flagged_now = edi.flicker_cycles(events, self._state, **self._args)
        return self._refresh_mask(), flagged_now

    def steps(self, events: np.ndarray) -> list[tuple[int, np.ndarray | None, np.ndarray]]:
        """Feed time-ordered events; flag changes take effect at the first event past the STEP_US span they were
        found in. Returns those points among the events: (index, the mask from there on or None if unchanged, the
        flat pixels newly flagged); a span still open at the end is taken by a later call, or by due()."""
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
