"""The DV network input's clock across server restarts.

A DV server that starts again sends times from before those edi-live already handed on: DV restarted on a file,
a dv-processing script that serves its recording once more, a reconnection (`--reconnect`) to a server whose
clock is older. The merge used to drop every event older than the newest one handed on, so the node fell silent
until the new clock passed the old one, and with a file served again that never happened. Here a stream whose
times go back by more than `restart_us` has restarted, and its times from there on continue right after
everything handed on: one offset per restart, shared by the camera's streams, which run on one clock (the first
stream that shows a restart sets the offset, the others take the same one when they show it too). When a frame
shows it first, the new clock's events from before that frame's exposure come out older than it and are dropped,
counted: after the gap EDI starts again at that frame, so they would serve no frame. Smaller steps back are
disorder and stay the merge's to drop, as before. A stream first seen after a restart runs on the newest clock.

Owns the offsets only: no sockets, no threads (drivers.dv_network's merge loop calls it on its own thread).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import numpy as np

from edi_live.aedat4.header import STREAM_NAMES
from edi_live.datatypes import Frame

log = logging.getLogger(__name__)

RESTART_US = 100_000
"""A stream whose times go back by more than this restarted (DV sends ~1 ms event packets and frames every few
tens of ms, in order)."""



class DvClock:
    """`events`, `frame` and `stamped` return their input with the offset of its stream's current clock applied
    (the same object when the offset is 0); `on_restart` is called once per stream restart."""

    def __init__(self, on_restart: Callable[[], None] = lambda: None, restart_us: int = RESTART_US) -> None:
        self.restart_us = int(restart_us)
        self._on_restart = on_restart
        self._offsets = [0]  # by restart: what the n-th restart's times get added
        self._generation: dict[str, int] = {}  # stream type -> how many restarts it has shown
        self._last_raw: dict[str, int] = {}  # stream type -> its newest time as sent
        self.newest_us = -(2**62)  # newest time handed on, any stream, offsets applied
        self.restarts = 0

    def events(self, array: np.ndarray, kind: str = "EVTS") -> np.ndarray:
        """An events, IMU or trigger array (field "t", in time order)."""
        if not len(array):
            return array
        offset = self._offset(kind, int(array["t"][0]), int(array["t"][-1]))
        if offset:
            array = array.copy()
            array["t"] += offset
        return array

    stamped = events

    def frame(self, frame: Frame) -> Frame:
        offset = self._offset("FRME", frame.exposure_start_us, frame.exposure_end_us)
        if not offset:
            return frame
        moved = {k: getattr(frame, k) + offset for k in ("start_us", "end_us") if getattr(frame, k) is not None}
        return dataclasses.replace(frame, exposure_start_us=frame.exposure_start_us + offset,
                                   exposure_end_us=frame.exposure_end_us + offset, **moved)

    def _offset(self, kind: str, first: int, last: int) -> int:
        before = self._last_raw.get(kind)
        if before is None:
            self._generation.setdefault(kind, len(self._offsets) - 1)  # a stream new here runs on the newest clock
        elif first < before - self.restart_us:
            generation = self._generation.get(kind, 0) + 1
            self._generation[kind] = generation
            first_to_show = generation == len(self._offsets)
            if first_to_show:
                self._offsets.append(self.newest_us + 1 - first)
                self.restarts += 1
            # one line per restart, not one per stream: the camera's other streams follow onto the same clock
            log.log(logging.WARNING if first_to_show else logging.DEBUG,
                    "the DV %s stream's clock went back %.3f s (its server started again, or serves a recording "
                    "again): its times now continue after the earlier ones (%+d µs)",
                    STREAM_NAMES.get(kind, kind), (before - first) / 1e6, self._offsets[generation])
            self._on_restart()
            before = None
        self._last_raw[kind] = last if before is None else max(before, last)
        offset = self._offsets[self._generation.get(kind, 0)]
        self.newest_us = max(self.newest_us, last + offset)
        return offset
