"""Packets in recording time -> the device's word stream in ~1 ms parts of device time, for the emulator.

Holds events back (`holdback_us`) so that a frame, which arrives after the events of its exposure, can still be
sent at its exposure start; maps recording time to device time (`shift` = recording time of device time 0),
injects a mid-stream timestamp reset (`reset_at_us`) and loops a recording with time that keeps increasing.
Pure: no pacing, no threads, no pyusb.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Iterator

import numpy as np

from drivers.davis.encoder import WordEncoder
from edi_live.datatypes import Packet


class WordStream:
    """Packets -> device-time word blocks, holding events back so a frame's exposure-start block (known only
    when the frame arrives after its events) lands in time order."""

    def __init__(self, factory: Callable[[], Iterable[Packet]], enc: WordEncoder, loop: bool, holdback_us: int,
                 reset_at_us: int | None) -> None:
        self.factory, self.enc, self.loop, self.holdback_us = factory, enc, loop, holdback_us
        self.reset_at_us = reset_at_us
        self.it: Iterator[Packet] = iter(factory())
        self.shift: int | None = None   # recording time of device time 0
        self.ev: list[np.ndarray] = []
        self.blocks: list[tuple[int, int, int, Any]] = []  # (t, order, n, payload)
        self.latest = None
        self.done = False       # everything encoded
        self.exhausted = False  # the packet iterator has ended
        self._n = 0

    def _add(self, pkt: Packet) -> None:
        times = [int(pkt.events["t"][0])] if len(pkt.events) else []
        times += [f.exposure_start_us for f in pkt.frames] + [int(x) for x in pkt.imu["t"][:1]]
        times += [int(x) for x in pkt.triggers["t"][:1]]
        if self.shift is None and times:
            self.shift = min(times)
        if len(pkt.events):
            self.ev.append(pkt.events)
            self.latest = max(self.latest or -(2**62), int(pkt.events["t"][-1]))
        for f in pkt.frames:
            self._block(f.exposure_start_us, 0, ("fs", f))
            self._block(f.exposure_end_us, 1, ("fe", f))
        for s in pkt.imu:
            self._block(int(s["t"]), 1, ("imu", s))
        for tr in pkt.triggers:
            self._block(int(tr["t"]), 1, ("trig", int(tr["type"])))

    def _block(self, t: int, order: int, payload: Any) -> None:
        self._n += 1
        self.blocks.append((t, order, self._n, payload))

    def ensure_shift(self) -> None:
        """Read packets (without encoding) until the recording time of device time 0 is known."""
        while self.shift is None and not self.exhausted:
            try:
                self._add(next(self.it))
            except StopIteration:
                self.exhausted = True

    def next_block(self) -> list[tuple[np.ndarray, int]] | None:
        """The next (words, device time reached) parts, or None at the end of the recording."""
        while not self.done:
            if not self.exhausted:
                try:
                    self._add(next(self.it))
                except StopIteration:
                    self.exhausted = True
            if self.exhausted:
                words = self._encode_until(2**62)
                if self.loop and self.shift is not None:
                    self._restart_loop()
                else:
                    self.done = True
            elif self.latest is None:
                continue
            else:
                words = self._encode_until(self.latest - self.holdback_us)
            if words is not None:
                return words
        return None

    def _restart_loop(self) -> None:
        last_dev = self.enc.last_t
        self.it = iter(self.factory())
        self.exhausted = False
        self.latest = None
        saved, self.shift = self.shift, None
        self.ensure_shift()
        if self.shift is None:  # an empty recording
            self.done, self.shift = True, saved
            return
        self.shift -= last_dev + 1000  # continue device time 1 ms after the previous pass

    def _encode_until(self, horizon: int) -> list[tuple[np.ndarray, int]] | None:
        """Encode everything up to `horizon` (recording time) as (words, device time reached) parts of at most
        ~1 ms of device time each, so pacing releases data as a camera would (early-packet delay 1 ms)."""
        if self.shift is None:
            return None
        ev = np.concatenate(self.ev) if self.ev else None
        self.ev = []
        if ev is not None:
            k = int(np.searchsorted(ev["t"], horizon, side="right"))
            if k < len(ev):
                self.ev = [ev[k:]]
            ev = ev[:k]
        self.blocks.sort(key=lambda b: (b[0], b[1], b[2]))
        due = [b for b in self.blocks if b[0] <= horizon]
        self.blocks = [b for b in self.blocks if b[0] > horizon]
        parts: list[tuple[np.ndarray, int]] = []
        pos = 0
        ts = ev["t"] if ev is not None else np.zeros(0, np.int64)
        for t, order, _, payload in due:
            k = int(np.searchsorted(ts, t, side="right"))
            if k > pos:
                parts += self._events(ev[pos:k])
                pos = k
            parts += [(w, self.enc.last_t) for w in self._payload(t, payload)]
        if ev is not None and pos < len(ev):
            parts += self._events(ev[pos:])
        return parts or None

    def _dev(self, t: int) -> int:
        """Device time of a block at recording time t. A block older than words already encoded (a frame that
        arrived more than holdback_us after its exposure start) is sent now, stamped with the latest device time:
        a device clock never goes backwards. Its data is delivered, only its time moves later."""
        return max(int(t) - self.shift, self.enc.last_t)

    def _maybe_reset(self, next_dev_t: int) -> list[np.ndarray]:
        if self.reset_at_us is not None and next_dev_t >= self.reset_at_us and self.enc.started:
            self.reset_at_us = None
            self.shift += self.enc.last_t
            return [self.enc.timestamp_reset()]
        return []

    def _events(self, ev: np.ndarray) -> list[tuple[np.ndarray, int]]:
        out: list[tuple[np.ndarray, int]] = []
        t = ev["t"].astype(np.int64) - self.shift
        if self.reset_at_us is not None and len(t) and t[-1] >= self.reset_at_us:
            k = int(np.searchsorted(t, self.reset_at_us, side="left"))
            out += self._event_slices(ev[:k])
            out += [(w, 0) for w in self._maybe_reset(int(t[k]) if k < len(t) else int(t[-1]))]
            ev = ev[k:]
        return out + self._event_slices(ev)

    def _event_slices(self, ev: np.ndarray, slice_us: int = 1000) -> list[tuple[np.ndarray, int]]:
        if not len(ev):
            return []
        t = np.maximum(ev["t"].astype(np.int64) - self.shift, self.enc.last_t)
        cuts = np.searchsorted(t, np.arange(t[0] + slice_us, t[-1] + 1, slice_us), side="left")
        out = []
        for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(t)]])):
            if b > a:
                out.append((self.enc.encode_events(t[a:b], ev["x"][a:b], ev["y"][a:b], ev["p"][a:b]),
                            int(t[b - 1])))
        return out

    def _payload(self, t: int, payload: Any) -> list[np.ndarray]:
        kind, obj = payload
        out = self._maybe_reset(int(t) - self.shift)
        d = self._dev(t)
        if kind == "fs":
            out.append(self.enc.encode_frame_start(d, obj))
        elif kind == "fe":
            out.append(self.enc.encode_frame_end(d, obj))
        elif kind == "imu":
            out.append(self.enc.encode_imu(d, obj["accel_g"], obj["gyro_dps"], float(obj["temperature_c"])))
        else:
            out.append(self.enc.encode_trigger(d, obj))
        return out
