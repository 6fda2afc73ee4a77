"""The DV network output: sharp frames (or the input events) served as an AEDAT4 stream over TCP.

What iniVation's DV (its "network TCP server" output module) and dv-processing's `NetworkWriter` serve, so DV's GUI
and dv-processing's `NetworkReader` consume edi-live unchanged. The protocol, checked byte by byte against
dv-processing 2.0.4's NetworkWriter (tests/edi_live/test_dv_output.py): the server never reads from its clients;
each client, on connecting, first receives the IOHeader (the size-prefixed "IOHE" FlatBuffer of an AEDAT4 file,
without the `#!AER-DAT4.0` line, `dataTablePosition` -1, an infoNode XML declaring ONE stream, id 0, with
`typeIdentifier`, `sizeX`/`sizeY` and `source`), then packets exactly as in a file: int32 stream id, int32 size,
the (by default uncompressed) payload. One stream per server, as in DV: frames on one port, events on another.

Owns: the listening socket and its thread ([dv-output-frames] / [dv-output-events]), which accepts clients,
encodes (edi_live.aedat4.writer's payload functions) and fans every packet out with non-blocking sends.
Never stalls the caller: `submit()` only appends to a bounded inbox (oldest dropped when full), and each client
has a bounded queue of whole packets; a client that reads too slowly (or not at all) loses its oldest unsent
packets, counted in `dropped`, and never holds up the others. The client slots (`max_clients`, 10 as in DV) cannot
be held by clients that never read: when the server is full, a newcomer first takes the slot of a client that has
gone (its end of the connection not yet seen), then that of the client stalled longest (its queue full and nothing
taken for `stall_s`), which is dropped with one line naming it; with no such client the newcomer is refused.
Frames keep a time-ordered stream (DV's recorders reject a stream that goes back in time): in causal mode an APS
frame's deblurred keyframe comes after newer latent frames, so frames are put back in order (edi_live.frame_order)
before they are sent, each held at most `hold_s` of wall time; a frame older than one already sent is skipped and
counted in `late`. (Skipping was all there was before: 138 of 148 deblurred frames of a looped real recording never
reached a DV client.)
"""

from __future__ import annotations

import collections
import errno
import logging
import selectors
import socket
import struct
import threading
import time
from typing import Any, Callable

from edi_live.aedat4 import schema as S
from edi_live.aedat4.compression import compressor
from edi_live.aedat4.writer import events_payloads, frame_payload, info_xml, io_header
from edi_live.checks import parse_tcp_endpoint
from edi_live.datatypes import Frame, Packet, Reconstruction
from edi_live.errors import BindError, PublishError
from edi_live.frame_order import FrameOrder

log = logging.getLogger(__name__)

STREAMS = {"frames": "FRME", "events": "EVTS"}
DEFAULT_MAX_CLIENTS = 10  # as DV's and dv-processing's servers
DEFAULT_CLIENT_QUEUE = 32  # packets waiting per client before its oldest are dropped
DEFAULT_INBOX = 256
DEFAULT_HOLD_S = 0.1  # wall time a frame may wait for an older one (the deblurred keyframe) before it is sent
DEFAULT_STALL_S = 2.0  # a client whose queue is full and that took nothing for this long gives its slot to a newcomer
_BACKLOG = 64  # connections the kernel holds until they are accepted (a burst of them: a hostile client, a restart)
_ACCEPTS = 64  # connections accepted in one go; the clients are served between such batches
_CLIENT_LINES = 20  # log lines about clients connecting and leaving, before they are only counted
_STOP_FLUSH_S = 0.5  # at close, how long clients get to take what is already queued for them
_HEAD = struct.Struct("<ii")
# errors Linux's accept() passes on from the connection being accepted; accept(2): "treat them like EAGAIN"
_CLIENT_ACCEPT_ERRNOS = {getattr(errno, name) for name in ("EPROTO", "ENOPROTOOPT", "EHOSTDOWN", "ENONET",
                                                            "EHOSTUNREACH", "EOPNOTSUPP", "ENETUNREACH", "ENETDOWN",
                                                            "EPERM") if hasattr(errno, name)}
_RECONSTRUCTION = S.FRAME_SOURCES["reconstruction"]


class _Client:
    __slots__ = ("sock", "peer", "queue", "current", "in_header", "taken_s")

    def __init__(self, sock: socket.socket, peer: str, header: bytes) -> None:
        self.sock, self.peer = sock, peer
        self.queue: collections.deque[bytes] = collections.deque()
        self.current = memoryview(header)  # the header is never dropped: it is the first thing sent
        self.in_header = True
        self.taken_s = time.monotonic()  # when it last took bytes (or connected)


class DvOutput:
    """An AEDAT4-over-TCP server of one stream (`stream` "frames": Reconstructions; "events": the Packets' events).

    `start()` binds (BindError on failure) and starts the thread; `submit()` never blocks; `close()` gives clients
    a moment to take what is queued, then closes every socket. `on_error` receives a failure of the thread.
    """

    def __init__(self, endpoint: str, stream: str, width: int, height: int, *, camera_name: str = "edi-live",
                 compression: str = "none", client_queue: int = DEFAULT_CLIENT_QUEUE, inbox: int = DEFAULT_INBOX,
                 max_clients: int = DEFAULT_MAX_CLIENTS, hold_s: float = DEFAULT_HOLD_S,
                 stall_s: float = DEFAULT_STALL_S, on_error: Callable[[BaseException], None] | None = None) -> None:
        if stream not in STREAMS:
            raise ValueError(f"stream must be one of {', '.join(STREAMS)} (got {stream!r})")
        self.endpoint, self.stream = endpoint, stream
        self.host, self.port = parse_tcp_endpoint(endpoint, "--dv-output" if stream == "frames"
                                                  else "--dv-output-events")
        self.width, self.height, self.camera_name = width, height, camera_name
        self.client_queue, self.inbox_size, self.max_clients = client_queue, inbox, max_clients
        self.stall_s = stall_s
        self._compress = compressor(compression)
        xml = info_xml([(0, STREAMS[stream], stream)], width, height, camera_name, compression)
        self._header = io_header(compression, -1, xml)[0]
        self._on_error = on_error
        self.name = f"dv-output-{stream}"
        self.bound_endpoint = ""
        self.error: BaseException | None = None
        self._inbox: collections.deque[Any] = collections.deque()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._listener: socket.socket | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._clients: dict[int, _Client] = {}
        self._thread: threading.Thread | None = None
        self._last_t = -(2**63)  # events: the newest time sent
        # a frame goes out once no older one can come (edi_live.frame_order), or after hold_s at the latest
        self._order = (FrameOrder(0, widen=False, predict=True, hold_s=hold_s, max_held=inbox) if stream == "frames"
                       else None)
        self.sent = self.connections = 0
        # two counters, each written by one thread only (a shared `+=` from both could lose counts)
        self._inbox_dropped = 0  # the caller's: the server thread fell behind (under _lock)
        self._client_dropped = 0  # the server thread's: packets a slow client did not take
        self._client_lines = 0

    # ---------------------------------------------------------------- any thread

    def start(self) -> None:
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)
            family, _, _, _, address = infos[0]
            listener = socket.socket(family, socket.SOCK_STREAM)
        except OSError as exc:
            raise BindError(f"cannot serve DV on {self.endpoint}: {exc.strerror or exc} (use 127.0.0.1 or 0.0.0.0)"
                            ) from exc
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind(address)
            listener.listen(_BACKLOG)
        except OSError as exc:
            listener.close()
            why = "address already in use (another program holds that port)" if exc.errno == 98 else exc.strerror
            raise BindError(f"cannot serve DV on {self.endpoint}: {why}; choose another with "
                            f"{'--dv-output' if self.stream == 'frames' else '--dv-output-events'} "
                            f"tcp://127.0.0.1:PORT") from exc
        listener.setblocking(False)
        self._listener = listener
        host, port = listener.getsockname()[:2]
        self.bound_endpoint = f"tcp://{host if ':' not in host else f'[{host}]'}:{port}"
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> int:
        """Items lost: frames or packets dropped from a full inbox, and packets a slow client did not take."""
        return self._inbox_dropped + self._client_dropped

    def submit(self, item: Reconstruction | Packet) -> None:
        """Queue one reconstruction ("frames") or packet ("events") for every client; never waits."""
        with self._lock:
            if len(self._inbox) >= self.inbox_size:
                self._inbox.popleft()
                self._inbox_dropped += 1
            self._inbox.append(item)
        self._wake()

    def pending(self) -> int:
        """Items submitted but not yet handed to the clients' queues."""
        return len(self._inbox)

    def client_count(self) -> int:
        return len(self._clients)

    @property
    def late(self) -> int:
        """Frames skipped as older than one already sent."""
        return self._order.late if self._order is not None else 0

    def stats(self) -> dict[str, Any]:
        s = self.stream
        return {f"dv_{s}_sent": self.sent, f"dv_{s}_dropped": self.dropped, f"dv_{s}_clients": len(self._clients),
                f"dv_{s}_connections": self.connections, **({f"dv_{s}_late": self.late} if s == "frames" else {})}

    def __enter__(self) -> "DvOutput":
        """start(); the block's end closes the server."""
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise PublishError(f"{self.name} thread did not stop within {timeout_s} s")
        for sock in (self._wake_r, self._wake_w):
            sock.close()
        late = f", {self.late} skipped as older than a frame already sent" if self.late else ""
        behind = f", {self._inbox_dropped} dropped before encoding (the server fell behind)" if self._inbox_dropped else ""
        log.info("%s: %d packets sent to %d client connection(s), %d dropped for slow clients%s%s", self.name,
                 self.sent, self.connections, self._client_dropped, behind, late)

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except OSError:  # full (a wake-up is pending anyway) or closed
            pass

    # ---------------------------------------------------------------- the server thread

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        try:
            sel.register(self._listener, selectors.EVENT_READ, "accept")
            sel.register(self._wake_r, selectors.EVENT_READ, "wake")
            deadline = None
            while True:
                for key, mask in sel.select(timeout=self._select_timeout_s()):
                    if key.data == "accept":
                        self._accept(sel)
                    elif key.data == "wake":
                        self._drain_wake()
                    else:
                        self._service(sel, key.data, mask)
                self._fan_out(sel)
                if self._stop.is_set():
                    if deadline is None:
                        deadline = time.monotonic() + _STOP_FLUSH_S
                    if not any(c.current or c.queue for c in self._clients.values()) or time.monotonic() > deadline:
                        return
        except BaseException as exc:  # noqa: BLE001 - handed to the node
            self.error = exc
            log.error("%s failed: %s", self.name, exc)
            if self._on_error is not None:
                self._on_error(exc)
        finally:
            for client in list(self._clients.values()):
                self._drop_client(sel, client, None)
            sel.close()
            if self._listener is not None:
                self._listener.close()

    def _select_timeout_s(self) -> float:
        due = self._order.next_due_s() if self._order is not None else None
        return 0.5 if due is None else min(0.5, max(0.0, due - time.monotonic()))

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except (BlockingIOError, InterruptedError):
            pass

    def _accept(self, sel: selectors.BaseSelector) -> None:
        """Accept what is waiting, up to _ACCEPTS at once: one per wake-up let a client connecting in a loop fill
        the kernel's backlog, and every further connection (a real viewer's too) waited a second for its SYN to
        be sent again."""
        for _ in range(_ACCEPTS):
            try:
                sock, addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if not isinstance(exc, ConnectionError) and exc.errno not in _CLIENT_ACCEPT_ERRNOS:
                    raise  # the server's own trouble (no file descriptors left, ...): the node's error line
                self._client_log(logging.INFO, "a DV client failed while connecting (%s)", exc.strerror or exc)
                continue
            self._admit(sel, sock, f"{addr[0]}:{addr[1]}")

    def _admit(self, sel: selectors.BaseSelector, sock: socket.socket, peer: str) -> None:
        if len(self._clients) >= self.max_clients and not self._make_room(sel, peer):
            self._client_log(logging.WARNING, "refused DV client %s (already %d clients)", peer, self.max_clients)
            sock.close()
            return
        try:
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:  # (EINVAL on some systems for a connection already reset)
            sock.close()
            self._client_log(logging.INFO, "DV client %s failed while connecting (%s)", peer, exc.strerror or exc)
            return
        client = _Client(sock, peer, self._header)
        self._clients[sock.fileno()] = client
        self.connections += 1
        sel.register(sock, selectors.EVENT_READ | selectors.EVENT_WRITE, client)
        self._client_log(logging.INFO, "DV client %s connected", peer)

    def _make_room(self, sel: selectors.BaseSelector, newcomer: str) -> bool:
        """A full server: drop the clients that have gone, else the one stalled longest. True if a slot is free."""
        for client in list(self._clients.values()):
            self._check_read(sel, client)
        if len(self._clients) < self.max_clients:
            return True
        now = time.monotonic()
        stalled = [c for c in self._clients.values()
                   if len(c.queue) >= self.client_queue and now - c.taken_s >= self.stall_s]
        if not stalled:
            return False
        victim = min(stalled, key=lambda c: c.taken_s)
        self._drop_client(sel, victim, None)
        self._client_log(logging.WARNING, "dropped DV client %s, which took nothing for %.1f s (its queue full), "
                         "to make room for %s", victim.peer, now - victim.taken_s, newcomer)
        return True

    def _check_read(self, sel: selectors.BaseSelector, client: _Client) -> bool:
        """Drop a client whose connection ended or that sent data; True if it is still there."""
        try:
            data = client.sock.recv(4096)
        except (BlockingIOError, InterruptedError):
            return True
        except OSError:
            data = b""
        # end of stream, or data a DV client must never send (DV closes then too)
        self._drop_client(sel, client, "disconnected" if not data else "sent data (not a DV client?)")
        return False

    def _service(self, sel: selectors.BaseSelector, client: _Client, mask: int) -> None:
        if mask & selectors.EVENT_READ and not self._check_read(sel, client):
            return
        if mask & selectors.EVENT_WRITE:
            self._send(sel, client)

    def _send(self, sel: selectors.BaseSelector, client: _Client) -> None:
        try:
            while True:
                if not client.current:
                    if not client.queue:
                        sel.modify(client.sock, selectors.EVENT_READ, client)
                        return
                    client.current = memoryview(client.queue.popleft())
                    client.in_header = False
                n = client.sock.send(client.current)
                client.current = client.current[n:]
                client.taken_s = time.monotonic()
                if not client.current and not client.in_header:
                    self.sent += 1
        except (BlockingIOError, InterruptedError):
            sel.modify(client.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, client)
        except OSError as exc:
            self._drop_client(sel, client, f"connection lost ({exc.strerror or exc})")

    def _drop_client(self, sel: selectors.BaseSelector, client: _Client, why: str | None) -> None:
        self._clients.pop(client.sock.fileno(), None)
        try:
            sel.unregister(client.sock)
        except (KeyError, ValueError):
            pass
        client.sock.close()
        if why:
            self._client_log(logging.INFO, "DV client %s %s", client.peer, why)

    def _client_log(self, level: int, message: str, *args: Any) -> None:
        """The first _CLIENT_LINES lines about clients coming and going; then silence (the closing line counts the
        connections), so that a client connecting in a loop cannot bury the node's status line."""
        self._client_lines += 1
        if self._client_lines <= _CLIENT_LINES:
            more = "; further client connections are only counted" if self._client_lines == _CLIENT_LINES else ""
            log.log(level, "%s: " + message + more, self.name, *args)

    def _fan_out(self, sel: selectors.BaseSelector) -> None:
        with self._lock:
            batch = list(self._inbox)
            self._inbox.clear()
        if self._order is not None:  # frames: back in time order first
            now = time.monotonic()
            for rec in batch:
                self._order.add(rec, now)
            batch = self._order.rest() if self._stop.is_set() else self._order.ready(now)
        for item in batch:
            for data in self._encode(item):
                for client in list(self._clients.values()):
                    if len(client.queue) >= self.client_queue:
                        client.queue.popleft()  # whole packets only: the one being sent is finished first
                        self._client_dropped += 1
                    client.queue.append(data)
        for client in list(self._clients.values()):
            if client.queue or client.current:
                self._send(sel, client)

    def _encode(self, item: Any) -> list[bytes]:
        if self.stream == "frames":
            rec: Reconstruction = item
            t = int(rec.t_us)
            payloads = [frame_payload(Frame(rec.image, t, t, start_us=t, end_us=t), _RECONSTRUCTION)]
        else:
            events = item.events
            if not len(events):
                return []
            if int(events["t"][0]) < self._last_t:  # a reconnected source may restart its clock: keep order
                events = events[events["t"] >= self._last_t]
                if not len(events):
                    return []
            self._last_t = int(events["t"][-1])
            payloads = [p for p, *_ in events_payloads(events)]
        out = []
        for payload in payloads:
            body = self._compress(payload)
            out.append(_HEAD.pack(0, len(body)) + body)
        return out

