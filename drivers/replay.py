"""AEDAT4 replay: a recording played back as if a camera were plugged in.

Owns `ReplaySource` (the `edi_live.source.Source` protocol: pacing by timestamps, `loop` with monotonic time,
`stop()` from any thread, counters). The packets come from `drivers.replay_merge.merged_packets` (re-exported
here), decoded on the iterating thread or, with `decode_process=True`, by `drivers.decoding_child`.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time
import warnings
from typing import Iterator

from drivers import decoding_child
from drivers.pacing import Pacer
from drivers.replay_merge import merged_packets, next_pass_offset
from edi_live.aedat4 import Aedat4Reader
from edi_live.datatypes import Packet, SourceInfo, SourceStatus
from edi_live.errors import ConfigError, RecordingError

__all__ = ["ReplaySource", "merged_packets"]


class ReplaySource:
    """Replays an AEDAT4 recording through the `Source` protocol, paced by its timestamps.

    speed 1 = real time (default), 4 = four times faster, 0 = as fast as possible. With `loop=True` the file restarts
    at its end and every timestamp of the next pass is shifted so time keeps increasing. Iteration yields `Packet`s,
    or None when nothing is due within `poll_s`; it ends at the end of the file, or soon after `stop()` (a stopped
    source stays stopped). A defect in the file raises `RecordingError` after every packet before it has been
    yielded. `decode_process=True` (what the CLI uses) decodes in a child process (drivers.decoding_child) and
    only paces here: the same packets, without the decoder's bursts on this process's GIL.
    """

    def __init__(self, path: str | os.PathLike, *, speed: float = 1.0, loop: bool = False,
                 max_packet_us: int | None = None, poll_s: float = 0.1, decode_process: bool = False) -> None:
        if not speed >= 0:
            raise ConfigError(f"--speed must be 0 (as fast as possible) or positive (got {speed})")
        self.path = os.fspath(path)
        self.speed, self.loop = float(speed), bool(loop)
        # paced: 1 ms packets, like a camera's USB transfers (low latency); unpaced: 10 ms packets (throughput)
        self.max_packet_us = max_packet_us if max_packet_us is not None else (1_000 if speed > 0 else 10_000)
        self.poll_s = poll_s
        # decode in a child process (drivers.decoding_child): keeps the decoder's bursts off this process's GIL
        self.decode_process = bool(decode_process)
        if self.decode_process:  # its server loads the decoder meanwhile: the first packet comes in milliseconds
            decoding_child.start_early()
        with Aedat4Reader(self.path) as reader:
            info = reader.source_info
            try:
                self._time_range = reader.time_range()
            except RecordingError:  # a damaged table does not stop the replay, which never needs it
                self._time_range = None
        if info.width <= 0 or info.height <= 0:
            raise RecordingError("the header gives no sensor resolution (sizeX/sizeY of the event or frame stream)",
                                 self.path, 0)
        self.info: SourceInfo = info
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._status = SourceStatus()
        self.loops = 0

    def __enter__(self) -> "ReplaySource":
        # (the stop flag is not cleared: a stop() that races ahead of __enter__ must still end the replay)
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        self._stop.set()

    def status(self) -> SourceStatus:
        with self._lock:
            return dataclasses.replace(self._status)

    def time_range(self) -> tuple[int, int] | None:
        """(first, last) µs of the recording from its FileDataTable, or None when the table has no timestamps."""
        return self._time_range

    def __iter__(self) -> Iterator[Packet | None]:
        pacer = Pacer(self.speed)
        seq = 0
        for packet in self._decoded() if self.decode_process else self._decode_here():
            if packet is None:
                yield None
                continue
            due = _last_time(packet)
            while not pacer.wait(due, self.poll_s, self._stop):
                if self._stop.is_set():
                    return
                yield None
            if self._stop.is_set():
                return
            if packet.frames:
                packet.frames = [dataclasses.replace(f, seq=seq + i) for i, f in enumerate(packet.frames)]
                seq += len(packet.frames)
            packet.arrival_ns = time.monotonic_ns()
            with self._lock:
                st = self._status
                st.packets += 1
                st.events += len(packet.events)
                st.frames += len(packet.frames)
            yield packet

    def _decode_here(self) -> Iterator[Packet]:
        """Every pass's packets, decoded on the calling thread."""
        offset = 0
        while not self._stop.is_set():
            span: dict = {}
            produced = False
            for packet in merged_packets(self.path, time_offset_us=offset, max_packet_us=self.max_packet_us,
                                         span=span, size=(self.info.width, self.info.height)):
                produced = True
                yield packet
                if self._stop.is_set():
                    return
            if not (self.loop and produced) or "t_first" not in span:
                return
            offset = next_pass_offset(offset, span)
            self.loops += 1

    def _decoded(self) -> Iterator[Packet | None]:
        """Every pass's packets, decoded by a child process (drivers.decoding_child); None while none is ready."""
        try:
            child = decoding_child.DecodeProcess(self.path, self.max_packet_us, self.loop,
                                                 size=(self.info.width, self.info.height))
        except (OSError, EOFError) as exc:  # no process can start here (limits, no /dev/shm): decode on this thread
            # (a forkserver that cannot fork shows up as EOFError)
            warnings.warn(f"{self.path}: cannot start the decoding process ({exc}); decoding in this process",
                          RuntimeWarning, stacklevel=2)
            yield from self._decode_here()
            return
        try:
            while not self._stop.is_set():
                try:
                    packet = child.next_packet(self.poll_s)
                except StopIteration:
                    return
                if self.loop:
                    self.loops = len(child.passes)
                yield packet
        finally:
            child.close()


def _last_time(packet: Packet) -> int:
    times = []
    if len(packet.events):
        times.append(int(packet.events["t"][-1]))
    times.extend(f.exposure_end_us for f in packet.frames)
    if len(packet.imu):
        times.append(int(packet.imu["t"].max()))
    if len(packet.triggers):
        times.append(int(packet.triggers["t"].max()))
    return max(times) if times else packet.watermark_us
