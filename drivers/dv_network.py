"""DV network input: events, APS frames, IMU and triggers from running DV instances or dv-processing NetworkWriters.

A DV network output (DV's "network TCP server" module, dv-processing's `NetworkWriter`) serves one stream per TCP
connection, as an AEDAT4 file without its magic line: the IOHeader (size-prefixed FlatBuffer with the infoNode XML
naming the stream's type, sensor size and camera), then packets (int32 stream id, int32 size, payload). So a DAVIS
in DV usually arrives on two or more endpoints (`--dv-input tcp://127.0.0.1:7777 --dv-input tcp://127.0.0.1:7778`);
each connection's stream type is read from its header (an optional `events=`, `frames=`, `imu=` or `triggers=`
prefix asserts it). Packets are decoded by edi_live.aedat4 (the same code that reads files).

Clocks: every stream of one camera carries its timestamps (Unix µs) on the camera's clock, so the streams share a
time base and only their arrival differs. The merge keeps the `Packet` ordering contract at the lowest latency:
events, IMU and triggers go out as they arrive; a frame is held until the events have reached its exposure end
(or for `frame_wait_s` at most, when events stall). A frame stream more than `max_clock_skew_us` away from the
event stream (two cameras, or DV replaying an old file on one output only) is refused with an error. A server that
starts again with an older clock (a recording served again) continues after the earlier times (drivers.dv_clock).

Care as in the USB driver: one reader thread per connection feeds one bounded queue; when the consumer falls
behind, the oldest queued event packets are dropped, counted, and the next packet is marked as a gap (frames, IMU
and triggers beyond `max_queued_frame_bytes` too, said in a warning: drivers.dv_queue). Faults
(connection refused, an unexpected stream type, a sensor-size change, a dropped connection, a corrupt packet) are
one-line `SourceError`s raised after everything received before them has been yielded (when one stream ends, the
others are read until they end too or stay silent for `end_grace_s`: DV closes its outputs one by one). With
`reconnect=True` a dropped connection is retried every `retry_s` until stop(); the same type and size must return.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from collections import Counter
from typing import Iterator, Sequence

from drivers import tcp_connect
from drivers.dv_clock import DvClock
from drivers.dv_queue import DvQueue
from edi_live.aedat4 import Aedat4Reader, StreamInfo
from edi_live.aedat4.header import STREAM_NAMES
from edi_live.aedat4.compression import decompressor
from edi_live.aedat4.reader import split_camera_label
from edi_live.datatypes import Frame, Packet, SourceInfo, SourceStatus
from edi_live.errors import (ConfigError, DeviceDisconnectedError, DeviceNotFoundError, ProtocolError, RecordingError,
                             SourceError)

log = logging.getLogger(__name__)

_NAMES = STREAM_NAMES
TYPES = {v: k for k, v in STREAM_NAMES.items()}
_HEAD = struct.Struct("<ii")
MAX_HEADER_BYTES = 1 << 20
MAX_PACKET_BYTES = 256 << 20
_READ_CHUNK = 1 << 20
_POLL_S = 0.2  # a reader blocked in recv() wakes up this often to check for stop()


def parse_dv_endpoint(spec: str) -> tuple[str | None, str, int]:
    """'[TYPE=]tcp://HOST:PORT' -> (expected type identifier or None, host, port); ConfigError otherwise (also for
    a value that is not text: a config file's `dv-input = [5]`)."""
    text = spec if isinstance(spec, str) else ""  # not text: refused below like any malformed endpoint
    kind, sep, endpoint = text.partition("=")
    if not sep:
        kind, endpoint = "", text
    scheme, sep, rest = endpoint.partition("://")
    host, _, port = rest.rpartition(":")
    host = host.strip("[]")
    if (kind and kind not in TYPES) or scheme != "tcp" or not sep or not host or not port.isdigit() \
            or not 0 < int(port) < 65536:
        raise ConfigError(f"--dv-input must look like [events=|frames=|imu=|triggers=]tcp://HOST:PORT, e.g. "
                          f"tcp://127.0.0.1:7777 (got {spec!r})")
    return (TYPES[kind] if kind else None), host, int(port)


class _Feed:
    """One connection: its header (stream types, sizes, camera) and the thread that reads and decodes packets."""

    def __init__(self, spec: str, owner: "DvNetworkSource") -> None:
        self.expect, self.host, self.port = parse_dv_endpoint(spec)
        self.where = f"tcp://{self.host}:{self.port}"
        self.owner = owner
        self.sock: socket.socket | None = None
        self.decoder: Aedat4Reader | None = None
        self.streams: dict[int, StreamInfo] = {}
        self.thread: threading.Thread | None = None
        self.header_deadline = 0.0

    def connect(self) -> None:
        """Connect and read the header; SourceError subclasses with one-line messages."""
        try:  # (a stop ends the connect too: a peer that drops SYNs held it for connect_timeout_s)
            sock = tcp_connect.connect(self.host, self.port, self.owner.connect_timeout_s, self.owner._stop)
        except ConnectionRefusedError:
            raise DeviceNotFoundError(f"cannot connect to the DV stream at {self.where}: connection refused (is DV's "
                                      f"network output or a dv-processing NetworkWriter serving there?)") from None
        except OSError as exc:
            raise DeviceNotFoundError(f"cannot connect to the DV stream at {self.where}: "
                                      f"{exc.strerror or exc}") from None
        if sock is None:
            raise _Stopped()
        try:
            # short waits, to see stop(), under one deadline for the whole header (a peer sending it byte by byte
            # does not reset it)
            sock.settimeout(_POLL_S)
            self.header_deadline = time.monotonic() + self.owner.connect_timeout_s
            size = struct.unpack("<I", self._read(sock, 4, "the stream header"))[0]
            if not 0 < size <= MAX_HEADER_BYTES:
                raise ProtocolError(f"{self.where} is not an AEDAT4 network stream (header size {size}); is it a DV "
                                    f"network output?")
            header = struct.pack("<I", size) + self._read(sock, size, "the stream header")
            try:
                decoder = Aedat4Reader.from_stream_header(header, self.where)
            except RecordingError as exc:
                raise ProtocolError(f"{self.where} sent no valid AEDAT4 header ({exc})") from None
            self._check_header(decoder)
        except BaseException:
            sock.close()
            raise
        self.sock, self.decoder = sock, decoder

    def _check_header(self, decoder: Aedat4Reader) -> None:
        streams = {s.id: s for s in decoder.streams}
        if not streams:
            raise ProtocolError(f"{self.where}: the stream header declares no stream")
        if len(streams) < len(decoder.streams):  # the packets could not say which stream they belong to
            raise ProtocolError(f"{self.where}: the stream header declares stream id "
                                f"{Counter(s.id for s in decoder.streams).most_common(1)[0][0]} twice")
        for s in streams.values():
            if s.type not in _NAMES:
                raise ProtocolError(f"{self.where} serves a {s.type} stream ('{s.name}'); --dv-input takes events "
                                    f"(EVTS), frames (FRME), imu (IMUS) or triggers (TRIG)")
            if self.expect is not None and s.type != self.expect:
                raise ProtocolError(f"{self.where} serves {_NAMES[s.type]} ({s.type}), not the "
                                    f"{_NAMES[self.expect]} its --dv-input prefix says")
            if s.type in ("EVTS", "FRME") and (s.width <= 0 or s.height <= 0):  # as a replayed file's header
                raise ProtocolError(f"{self.where}: the stream header gives the {_NAMES[s.type]} stream no sensor "
                                    f"size (sizeX/sizeY of its info node missing, zero or negative)")
        twice, count = Counter(s.type for s in decoder.streams).most_common(1)[0]
        if count > 1:  # the node takes one stream of each type
            raise ProtocolError(f"{self.where}: the stream header declares {count} {_NAMES[twice]} streams; "
                                f"edi-live reads one stream of each type")
        if self.streams:  # a reconnection: the same streams, the same sensor
            old = {(s.type, s.width, s.height) for s in self.streams.values()}
            new = {(s.type, s.width, s.height) for s in streams.values()}
            if old != new:
                was, now = sorted(old)[0], sorted(new)[0]
                raise ProtocolError(f"the DV stream at {self.where} came back as {_NAMES.get(now[0], now[0])} "
                                    f"{now[1]}x{now[2]}, it was {_NAMES.get(was[0], was[0])} {was[1]}x{was[2]}: "
                                    f"a sensor change needs a restart of edi-live")
        self.streams = streams

    def _read(self, sock: socket.socket, n: int, what: str) -> bytes:
        # at most _READ_CHUNK at once: memory follows the bytes that arrive, not the size a peer announces
        parts: list[bytes] = []
        got = 0
        while got < n:
            try:
                chunk = sock.recv(min(n - got, _READ_CHUNK))
            except socket.timeout:
                chunk = None
            except OSError as exc:
                raise DeviceDisconnectedError(self._lost(f"connection lost ({exc.strerror or exc})")) from None
            if chunk == b"":
                raise DeviceDisconnectedError(self._lost("the server closed the connection"))
            if chunk:
                parts.append(chunk)
                got += len(chunk)
            # (checked after data too: a peer trickling bytes never lets recv() time out)
            if self.owner._stop.is_set():
                raise _Stopped()
            if self.sock is None and got < n and time.monotonic() >= self.header_deadline:  # still connecting
                raise ProtocolError(f"{self.where} accepted the connection but did not send {what} within "
                                    f"{self.owner.connect_timeout_s:g} s (an old DV without the network "
                                    f"header, or not a DV output?)")
        return parts[0] if len(parts) == 1 else b"".join(parts)

    def _lost(self, why: str) -> str:
        kinds = "+".join(_NAMES[s.type] for s in self.streams.values()) or "DV"
        hint = "" if self.owner.reconnect else "; rerun with --reconnect to wait for it to come back"
        return f"the DV {kinds} stream at {self.where} ended: {why} (DV stopped or its output was removed){hint}"

    def run(self) -> None:
        owner = self.owner
        try:
            while not owner._stop.is_set():
                try:
                    self._pump()
                except DeviceDisconnectedError as exc:
                    if not owner.reconnect or owner._stop.is_set():
                        raise
                    log.warning("%s; reconnecting", exc)
                    if not self._reconnect():
                        return
        except _Stopped:
            return
        except SourceError as exc:
            owner._queue.put(("fault", exc))
        except BaseException as exc:  # noqa: BLE001 - handed to the iterating thread as a source fault
            owner._queue.put(("fault", SourceError(f"DV reader for {self.where} failed: {type(exc).__name__}: {exc}")))

    def _pump(self) -> None:
        decode, decompress = self.decoder.decode_payload, decompressor(self.decoder.compression)
        pos, seq = 0, 0
        while not self.owner._stop.is_set():
            sid, size = _HEAD.unpack(self._read(self.sock, 8, "packet"))
            if not 0 < size <= MAX_PACKET_BYTES or sid not in self.streams:
                raise ProtocolError(f"{self.where}: corrupt packet header (stream {sid}, {size} bytes) after "
                                    f"{pos} bytes of packets")
            body = self._read(self.sock, size, "packet")
            arrival_ns = time.monotonic_ns()
            stream = self.streams[sid]
            try:
                payload = decompress(body)
            except Exception as exc:
                raise ProtocolError(f"{self.where}: a packet does not decompress ({exc})") from None
            data = decode(stream, pos, payload, seq)
            seq += stream.type == "FRME"
            pos += 8 + size
            self.owner._queue.put((stream.type, data, arrival_ns))

    def _reconnect(self) -> bool:
        if self.sock is not None:
            self.sock.close()
        self.sock = None
        self.owner._queue.mark_gap()
        while not self.owner._stop.wait(self.owner.retry_s):
            try:
                self.connect()
            except (DeviceNotFoundError, DeviceDisconnectedError):
                continue  # not back yet
            log.info("reconnected to the DV stream at %s", self.where)
            return True
        return False


class _Stopped(Exception):
    pass


class DvNetworkSource:
    """The `edi_live.source.Source` of one camera served by DV over TCP, one endpoint per stream (see module doc)."""

    def __init__(self, endpoints: Sequence[str], *, reconnect: bool = False, max_queued_events: int = 4_000_000,
                 max_queued_items: int = 100_000, max_queued_frame_bytes: int = 256 << 20,
                 connect_timeout_s: float = 5.0, retry_s: float = 0.5,
                 frame_wait_s: float = 1.0, max_clock_skew_us: int = 10_000_000, end_grace_s: float = 1.0) -> None:
        if not endpoints:
            raise ConfigError("--dv-input needs at least one endpoint, e.g. tcp://127.0.0.1:7777")
        self.reconnect = bool(reconnect)
        self.connect_timeout_s, self.retry_s, self.frame_wait_s = connect_timeout_s, retry_s, frame_wait_s
        self.max_clock_skew_us, self.end_grace_s = max_clock_skew_us, end_grace_s
        self._feeds = [_Feed(spec, self) for spec in endpoints]
        self.info = SourceInfo(0, 0, name="DV", kind="network")
        self._stop = threading.Event()
        self._status = SourceStatus()
        self._queue = DvQueue(self._status, max_queued_events, max_queued_items, max_queued_frame_bytes)

    # ---- Source protocol ----------------------------------------------------------------------------
    def __enter__(self) -> "DvNetworkSource":
        try:
            for feed in self._feeds:
                feed.connect()
            self.info = self._combined_info()
        except _Stopped:  # stop() while a server was still sending its header: nothing to read, iteration ends
            self._close()
            return self
        except BaseException:
            self._close()
            raise
        for feed in self._feeds:
            feed.thread = threading.Thread(target=feed.run, name=f"dv-input-{feed.port}", daemon=True)
            feed.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self._close()

    def stop(self) -> None:
        self._stop.set()
        self._queue.wake()

    def status(self) -> SourceStatus:
        self._status.backlog = self._queue.queued_events
        return self._status

    def __iter__(self) -> Iterator[Packet | None]:
        held: list[tuple[float, Frame]] = []  # frames waiting for their events: (wall-clock arrival, frame)
        events_to = -(2**62)  # newest event time yielded
        frame_clock_checked = False
        clock = DvClock(self._queue.mark_gap)  # a server starting again: its times continue after the earlier ones
        ended: SourceError | None = None  # a stream ended while others still deliver: raised once they are done
        last_item = time.monotonic()
        st = self._status
        while not self._stop.is_set():
            item = self._queue.get(0.1, self._stop)
            fault = None
            packet = Packet()
            if item is not None and item[0] != "fault":
                last_item = time.monotonic()
            if item is None:
                if ended is not None and (time.monotonic() - last_item >= self.end_grace_s
                                          or not any(f.thread.is_alive() for f in self._feeds)):
                    fault = ended
            elif item[0] == "fault":
                if isinstance(item[1], DeviceDisconnectedError) and any(f.thread.is_alive() for f in self._feeds):
                    ended = ended or item[1]
                else:
                    fault = ended or item[1]
            elif item[0] == "EVTS":
                events = clock.events(item[1])
                if len(events) and int(events["t"][0]) < events_to:  # disorder (a restart is dv_clock's)
                    keep = events["t"] >= events_to
                    st.dropped_events += int(len(events) - keep.sum())
                    events = events[keep]
                    self._queue.mark_gap()
                if len(events):
                    events_to = int(events["t"][-1])
                    packet.events, packet.arrival_ns = events, item[2]
            elif item[0] == "FRME":
                frame: Frame = clock.frame(item[1])
                if frame.image.shape[:2] != (self.info.height, self.info.width):
                    fault = ProtocolError(f"a DV frame of {frame.width}x{frame.height} arrived on a "
                                          f"{self.info.width}x{self.info.height} sensor (sensor size changed?)")
                else:
                    if not frame_clock_checked and events_to > -(2**62):
                        frame_clock_checked = True
                        skew = frame.exposure_end_us - events_to
                        if abs(skew) > self.max_clock_skew_us:
                            fault = SourceError(f"the DV frames are {skew / 1e6:+.1f} s away from the DV events: "
                                                f"the --dv-input endpoints do not serve one camera's clock")
                    if fault is None:
                        held.append((time.monotonic(), frame))
                        packet.arrival_ns = item[2]
            else:
                setattr(packet, "imu" if item[0] == "IMUS" else "triggers", clock.stamped(item[1], item[0]))
            now = time.monotonic()
            due = [f.exposure_end_us <= events_to or now - arrived >= self.frame_wait_s or fault is not None
                   for arrived, f in held]
            if any(due):
                packet.frames = sorted((f for (_, f), d in zip(held, due) if d), key=lambda f: f.exposure_end_us)
                held = [h for h, d in zip(held, due) if not d]
            if len(packet.events) or packet.frames or len(packet.imu) or len(packet.triggers):
                packet.watermark_us = events_to
                packet.gap = self._queue.take_gap()
                st.packets += 1
                st.events += len(packet.events)
                st.frames += len(packet.frames)
                yield packet
            elif item is None:
                yield None
            if fault is not None:
                raise fault

    # ---- internals ----------------------------------------------------------------------------------
    def _combined_info(self) -> SourceInfo:
        streams = [s for feed in self._feeds for s in feed.streams.values()]
        types = [s.type for s in streams]
        dupes = sorted({_NAMES[t] for t in types if types.count(t) > 1})
        if dupes:
            raise ConfigError(f"--dv-input: two endpoints serve {', '.join(dupes)}; give one endpoint per stream type")
        if "EVTS" not in types:
            raise ConfigError("--dv-input: no endpoint serves events, which EDI needs (add the events output's "
                              "endpoint)")
        sizes = {(s.width, s.height) for s in streams if s.type in ("EVTS", "FRME")}
        if len(sizes) > 1:
            raise SourceError(f"the DV streams disagree on the sensor size ({', '.join(f'{w}x{h}' for w, h in sizes)})")
        w, h = sizes.pop()
        cameras = sorted({s.source for s in streams if s.source})
        if len(cameras) > 1:
            log.warning("the DV streams name different cameras (%s); using the events stream's", ", ".join(cameras))
        events_camera = next((s.source for s in streams if s.type == "EVTS" and s.source), "")
        name, serial = split_camera_label(events_camera or "DV")
        return SourceInfo(w, h, name=name, serial=serial, kind="network",
                          color_filter=next((s.color_filter for s in streams if s.color_filter), None))

    def _close(self) -> None:
        self._queue.report_drops()
        self._stop.set()
        for feed in self._feeds:
            if feed.thread is not None:
                feed.thread.join(timeout=2.0)
            if feed.sock is not None:
                feed.sock.close()
                feed.sock = None

