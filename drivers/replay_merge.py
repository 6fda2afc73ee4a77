"""The AEDAT4 replay merge: a recording's streams merged into time-ordered `Packet`s.

Owns `merged_packets()` (honouring the ordering contract of `edi_live.datatypes.Packet`). `drivers.replay` paces
these packets as a `Source`; `drivers.decoding_child` runs this merge in a child process.

Why a merge: DV writes packets in arrival order, so a frame packet arrives ~17 ms after the events of its exposure,
and a trigger packet can precede older events. The merge keeps, per primary stream (the first EVTS, FRME, IMUS and
TRIG stream), the newest key seen (events: t, frames: exposure end, IMU and triggers: t); every item below the
smallest of those keys is final and is emitted. A frame goes out right after the events up to its exposure end.
Memory is bounded: a stream silent for more than `horizon_us` of sensor time stops holding the others back, and
more than `max_pending_events` buffered events force emission of the events (frames then follow their events late,
which the contract allows). So the merge holds at most one file packet plus min(horizon, cap) of data.
"""

from __future__ import annotations

import bisect
import dataclasses
import os
import time
import warnings
from typing import Iterator

import numpy as np

from edi_live.aedat4 import Aedat4Reader
from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, TRIGGER_DTYPE, Frame, Packet, concat_events
from edi_live.errors import RecordingError

_NAMES = {"EVTS": "event", "FRME": "frame", "IMUS": "IMU", "TRIG": "trigger"}
_NEG_INF = -(2**62)
_POS_INF = 2**62


class _Merger:
    """The k-way merge state; feed() one decoded file packet at a time, emit() the packets now final."""

    def __init__(self, path: str, types: list[str], offset_us: int, max_packet_us: int, horizon_us: int,
                 max_pending_events: int) -> None:
        self.path, self.offset_us = path, offset_us
        self.max_packet_us, self.horizon_us, self.max_pending_events = max_packet_us, horizon_us, max_pending_events
        self.last = {t: _NEG_INF for t in types}  # newest key seen per primary stream type
        self.max_key = _NEG_INF
        self.max_key_from = ("EVTS", 0)  # the stream and byte of the packet that holds max_key
        self.emitted_to = _NEG_INF  # exclusive bound already emitted
        self.events: list[tuple[int, int, np.ndarray]] = []  # (t_first, t_last, events)
        self.n_events = 0
        self.frames: list[tuple[int, int, Frame]] = []  # (exposure end, arrival order, frame)
        self.frame_start = _NEG_INF  # the newest frame's exposure start: frames come in time order
        self.imu: list[tuple[int, int, np.ndarray]] = []
        self.triggers: list[tuple[int, int, np.ndarray]] = []
        self.order = 0
        self.t_first, self.t_last = _POS_INF, _NEG_INF  # span of all timestamps (for --loop)

    def _span(self, lo: int, hi: int) -> None:
        self.t_first, self.t_last = min(self.t_first, lo), max(self.t_last, hi)

    def feed(self, kind: str, pos: int, data) -> None:
        off = self.offset_us
        if kind == "EVTS":
            if not len(data):
                return
            if off:
                data = _shifted(data, off)
            t0, t1 = int(data["t"][0]), int(data["t"][-1])
            if t0 < self.last["EVTS"]:
                raise RecordingError(f"event packet starts at {t0 - off} µs, before events already read "
                                     f"(events out of time order)", self.path, pos)
            if t0 < self.emitted_to:  # in order among the events: another stream's timestamp ran far ahead
                kind_ahead, pos_ahead = self.max_key_from
                raise RecordingError(f"event packet starts at {t0 - off} µs, {(self.max_key - t0) / 1e6:.1f} s "
                                     f"behind the {_NAMES[kind_ahead]} timestamp {self.max_key - off} µs read at "
                                     f"byte {pos_ahead}: the streams are more than {self.horizon_us / 1e6:g} s "
                                     f"out of step (a damaged timestamp?)", self.path, pos)
            self.events.append((t0, t1, data))
            self.n_events += len(data)
            key_lo, key = t0, t1
        elif kind == "FRME":
            if off:
                data = dataclasses.replace(data, exposure_start_us=data.exposure_start_us + off,
                                           exposure_end_us=data.exposure_end_us + off,
                                           start_us=None if data.start_us is None else data.start_us + off,
                                           end_us=None if data.end_us is None else data.end_us + off)
            key_lo, key = data.exposure_start_us, data.exposure_end_us
            if key_lo < self.frame_start:  # EDI would take it as the newest reference, seconds in the past
                raise RecordingError(f"frame exposure starts at {key_lo - off} µs, before the previous frame's "
                                     f"{self.frame_start - off} µs (frames out of time order)", self.path, pos)
            self.frame_start = key_lo
            self.order += 1
            bisect.insort(self.frames, (key, self.order, data), key=lambda f: (f[0], f[1]))
        else:
            if not len(data):
                return
            if off:
                data = data.copy()
                data["t"] += off
            t = data["t"]
            if len(t) > 1 and bool((t[1:] < t[:-1]).any()):
                data = data[np.argsort(t, kind="stable")]
                t = data["t"]
            key_lo, key = int(t[0]), int(t[-1])
            (self.imu if kind == "IMUS" else self.triggers).append((key_lo, key, data))
        self._span(key_lo, key)
        self.last[kind] = max(self.last[kind], key)
        if key > self.max_key:
            self.max_key, self.max_key_from = key, (kind, pos)

    def bound(self) -> int:
        """Exclusive time bound below which everything has been read."""
        floor = self.max_key - self.horizon_us
        w = min(max(k, floor) for k in self.last.values())
        if self.n_events > self.max_pending_events and "EVTS" in self.last:
            w = max(w, self.last["EVTS"])
        return w

    def emit(self, w: int) -> Iterator[Packet]:
        """Packets holding everything with key < w, split at frame exposure ends and every max_packet_us."""
        if w <= self.emitted_to and not self._late_pending(w):
            return
        events = _take(self.events, w, EVENT_DTYPE)
        self.n_events -= len(events)
        frames = []
        while self.frames and self.frames[0][0] < w:
            frames.append(self.frames.pop(0)[2])
        imu = _take(self.imu, w, IMU_DTYPE)
        trig = _take(self.triggers, w, TRIGGER_DTYPE)
        lo = self.emitted_to
        if w > self.emitted_to:
            self.emitted_to = w
        if not (len(events) or frames or len(imu) or len(trig)):
            return
        yield from _split(events, frames, imu, trig, lo, max(w, lo), self.max_packet_us)

    def _late_pending(self, w: int) -> bool:
        return bool((self.frames and self.frames[0][0] < w) or (self.imu and self.imu[0][0] < w)
                    or (self.triggers and self.triggers[0][0] < w))


def _shifted(events: np.ndarray, offset_us: int) -> np.ndarray:
    """A copy of events (EVENT_DTYPE) with `offset_us` added to t, copied as raw int64 pairs (t is the first
    8 bytes of the 16-byte record): ~4x cheaper than a structured copy plus a strided field add."""
    raw = np.ascontiguousarray(events).view(np.int64).reshape(-1, 2).copy()
    raw[:, 0] += offset_us
    return raw.view(EVENT_DTYPE).reshape(-1)


def _take(chunks: list[tuple[int, int, np.ndarray]], w: int, dtype: np.dtype) -> np.ndarray:
    """Pop the items with t < w from a list of (t_first, t_last, t-sorted array) chunks. Whole chunks are taken
    without copying and at most one is split, so a call costs O(items taken), not O(items pending)."""
    taken = []
    while chunks and chunks[0][1] < w:
        taken.append(chunks.pop(0)[2])
    if chunks and chunks[0][0] < w:
        _, t1, head = chunks[0]
        i = int(np.searchsorted(head["t"], w, side="left"))
        taken.append(head[:i])
        chunks[0] = (int(head["t"][i]), t1, head[i:])
    if not taken:
        return np.zeros(0, dtype=dtype)
    if len(taken) == 1:
        return taken[0]
    if dtype == EVENT_DTYPE:
        return concat_events(taken)
    return np.concatenate(taken)  # IMU and triggers: unpadded dtypes, few items


def _slot_cuts(t: np.ndarray, max_packet_us: int) -> list[int]:
    """Starts of the max_packet_us slots (multiples of it) that events enter, after the first event's slot.
    Found by searching the few slot starts in the sorted times (O(slots log n)); per-event division cost ~5 µs
    per 1000 events. Falls back to the per-event form when the batch spans more slots than it has events."""
    q0, q1 = int(t[0]) // max_packet_us, int(t[-1]) // max_packet_us
    if q1 - q0 > len(t):
        q = t // max_packet_us
        return (q[np.flatnonzero(q[1:] != q[:-1]) + 1] * max_packet_us).tolist()
    starts = np.arange(q0 + 1, q1 + 1, dtype=np.int64) * max_packet_us
    idx = np.searchsorted(t, starts, side="left")
    # a slot is entered when the first event at or after its start lies inside it (idx < len: q1's slot is)
    inside = t[np.minimum(idx, len(t) - 1)] < starts + max_packet_us
    return starts[inside & (idx < len(t))].tolist()


def _split(events: np.ndarray, frames: list[Frame], imu: np.ndarray, trig: np.ndarray, lo: int, w: int,
           max_packet_us: int) -> Iterator[Packet]:
    t = events["t"]
    start = int(t[0]) if len(t) else (lo if lo > _NEG_INF else w)
    if lo <= _NEG_INF:
        lo = start
    cuts = {f.exposure_end_us + 1 for f in frames if lo < f.exposure_end_us + 1 < w}
    if len(t) and max_packet_us > 0 and int(t[-1]) - start >= max_packet_us:
        cuts.update(_slot_cuts(t, max_packet_us))
    bounds = sorted(c for c in cuts if lo < c < w) + [w]
    ev_idx = np.searchsorted(t, bounds, side="left")
    imu_idx = np.searchsorted(imu["t"], bounds, side="left")
    trig_idx = np.searchsorted(trig["t"], bounds, side="left")
    fi, e0, i0, g0 = 0, 0, 0, 0
    now = time.monotonic_ns()
    for k, hi in enumerate(bounds):
        e1, i1, g1 = int(ev_idx[k]), int(imu_idx[k]), int(trig_idx[k])
        fs = []
        while fi < len(frames) and frames[fi].exposure_end_us < hi:
            fs.append(frames[fi])
            fi += 1
        if e1 > e0 or fs or i1 > i0 or g1 > g0:
            watermark = hi if k < len(bounds) - 1 else w
            yield Packet(events=events[e0:e1], frames=fs, imu=imu[i0:i1], triggers=trig[g0:g1],
                         watermark_us=watermark, arrival_ns=now)
        e0, i0, g0 = e1, i1, g1


MIN_PASS_US = 1_000
"""Shortest pass of a looped replay (sensor µs): a recording of one instant (one event, one frame) would otherwise
repeat every 1 µs, a pass per µs of the replay clock, and keep a core busy at any --speed."""


def next_pass_offset(offset_us: int, span: dict) -> int:
    """The time offset of a looped replay's next pass: after the pass that `merged_packets` described in `span`
    (its first and last timestamps), one µs later, and at least MIN_PASS_US after the pass's start."""
    return offset_us + max(span["t_last"] - span["t_first"] + 1, MIN_PASS_US)


def merged_packets(path: str | os.PathLike, *, time_offset_us: int = 0, max_packet_us: int = 10_000,
                   horizon_us: int = 1_000_000, max_pending_events: int = 4_000_000,
                   span: dict | None = None, size: tuple[int, int] | None = None) -> Iterator[Packet]:
    """Time-ordered `Packet`s of an AEDAT4 file (all streams merged), with bounded memory.

    Events are sorted by t across packets; each frame comes in the packet that ends with the last event <= its
    exposure end; `watermark_us` says no later packet holds an event with t < watermark_us. `time_offset_us` is
    added to every timestamp (used by `--loop`). Packets span at most `max_packet_us` of event time. On a defect the
    packets before it are yielded, then `RecordingError` is raised. `span`, if given, receives 't_first'/'t_last'.
    `size` (width, height): the sensor the replay was set up for; a file of another one is a `RecordingError` (a
    --loop pass opens the file by its name again, and it may have been replaced meanwhile).
    """
    with Aedat4Reader(path, validate=True) as reader:  # each event packet: sorted and on the sensor
        info = reader.source_info
        if size is not None and (info.width, info.height) != tuple(size):
            raise RecordingError(f"the recording is now of a {info.width}x{info.height} sensor, not the "
                                 f"{size[0]}x{size[1]} one the replay started with: it was replaced while it was "
                                 "replayed", reader.path, 0)
        primary: dict[int, str] = {}
        for s in reader.streams:
            if s.supported and s.type not in primary.values():
                primary[s.id] = s.type
            elif s.supported:
                warnings.warn(f"{reader.path}: a second {s.type} stream ({s.id} '{s.name}') is not replayed",
                              RuntimeWarning, stacklevel=2)
        m = _Merger(reader.path, list(primary.values()), int(time_offset_us), max_packet_us, horizon_us,
                    max_pending_events)
        error: RecordingError | None = None
        try:
            for stream, pos, data in reader.records():
                kind = primary.get(stream.id)
                if kind is None:
                    continue
                m.feed(kind, pos, data)
                w = m.bound()
                # emit once per max_packet_us of progress (or when a frame is due), not once per file packet:
                # DV files hold ~1 kHz of tiny IMU packets, and each emission has a fixed cost
                if w - m.emitted_to >= max_packet_us or (m.frames and m.frames[0][0] < w):
                    yield from m.emit(w)
        except RecordingError as exc:
            error = exc
        # everything read before the end (or the defect) is final: deliver it, then report the defect
        last_event_t = m.last.get("EVTS", _NEG_INF)
        end_mark = (last_event_t if last_event_t > _NEG_INF else m.t_last) + 1
        for packet in list(m.emit(_POS_INF)):
            packet.watermark_us = min(packet.watermark_us, max(end_mark, m.t_first))
            yield packet
        if span is not None:
            span["t_first"], span["t_last"] = m.t_first, m.t_last
        if error is not None:
            raise error
