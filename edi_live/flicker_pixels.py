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

Between APS frames the flags found in a stream take effect at fixed points of the event clock (`note`, `due`):
at the first event past the STEP_US span they were found in. Taking them at the end of each read made the
latent frames depend on where the reads were cut.
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
        changed = int(self._state.changes[0]) != self._changes
        if changed:
            self._changes = int(self._state.changes[0])
            self._mask = self._state.flagged.reshape(self.height, self.width)
            self._count = int(np.count_nonzero(self._mask))
        return changed, flagged_now

    @staticmethod
    def spans(events: np.ndarray) -> list[np.ndarray]:
        """Time-ordered events cut where the event clock crosses a multiple of STEP_US."""
        span = events["t"] // STEP_US
        if span.size == 0 or span[0] == span[-1]:
            return [events]
        return np.split(events, np.flatnonzero(np.diff(span)) + 1)

    def note(self, events: np.ndarray) -> None:
        """observe() events of one span (see spans); what they change is taken by `due` after the span."""
        changed, flagged_now = self.observe(events)
        self._due_changed |= changed
        if flagged_now.size:
            self._due.append(flagged_now)
        self._due_span = int(events["t"][-1]) // STEP_US

    def due(self, t_us: int | None) -> tuple[bool, np.ndarray] | None:
        """Before the event at t_us (None: now, e.g. at an APS frame): (whether the mask changed, the pixels
        flagged) from the noted spans that ended before it, or None if nothing is due."""
        if not (self._due_changed or self._due) or (t_us is not None and t_us // STEP_US <= self._due_span):
            return None
        out = self._due_changed, (np.concatenate(self._due) if self._due else np.empty(0, np.int64))
        self._due, self._due_changed = [], False
        return out

    def reset(self) -> None:
        """Forget everything (a gap: the cycle timing no longer holds)."""
        self._state = edi.FlickerState(self.width, self.height)
        self._changes = 0
        self._mask = np.zeros((self.height, self.width), bool)
        self._count = 0
        self._due, self._due_changed = [], False
