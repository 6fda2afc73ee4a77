"""`edi_live.client`: subscribe to an edi-live publisher and get `(header, numpy image)` pairs
(`python -m edi_live.client [ENDPOINT]` prints one line per frame).

    from edi_live.client import subscribe
    for header, image in subscribe("tcp://127.0.0.1:5555"):
        print(header["seq"], header["t"], image.shape)  # (h, w) gray, or (h, w, 3) BGR from a colour camera

With `newest_only=True` (the default) each receive drains the socket and keeps the newest complete frame, so
a viewer that falls behind skips to the present instead of lagging (ZMQ_CONFLATE cannot be used: it keeps
only the last *part* of a multipart message). Every receive has a timeout or waits in short interruptible
slices. Malformed or oversized messages raise `ClientError`; a receive that times out raises `ClientTimeout`
(a `ClientError` and a `TimeoutError`) from `subscribe()`, or returns None from `Subscriber.recv()`. Handshakes
that keep failing (CURVE on one side only, a wrong key, a peer that is not ZeroMQ) raise `ClientHandshakeError`.

Memory is bounded before anything is received: libzmq refuses any message part over `max_bytes`
(ZMQ_MAXMSGSIZE, checked against the part's length prefix, so nothing is allocated) by dropping the connection,
and the receive queue holds at most `max_queued_bytes // max_bytes` messages (ZMQ_RCVHWM). A dropped
connection is re-established by the client itself (libzmq does not reconnect after a protocol error).

The SUB sockets use TCP keepalive, not ZMTP heartbeats, to notice a vanished publisher: libzmq 4.3 aborts
("Assertion failed: _input_stopped (stream_engine_base.cpp)") when a heartbeat timeout fires while the receive
queue is full (a slow reader) and the reconnected engine inherits the full queue. Keepalive errors surface only
when the engine reads, which it does not while the queue is full.
"""

from __future__ import annotations

import argparse
import math
import numbers
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import zmq
from zmq.utils.monitor import parse_monitor_message

from edi_live import wire
from edi_live.checks import ipv6_literal, tcp_parts
from edi_live.curve_keys import check_z85, load_certificate
from edi_live.errors import ClientError

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"
DEFAULT_MAX_BYTES = wire.DEFAULT_MAX_BYTES
DEFAULT_MAX_QUEUED_BYTES = 1 << 30
"""The receive queue's bound: RCVHWM is capped at max_queued_bytes // max_bytes messages (16 by default)."""
_SLICE_S = 0.1  # longest single wait, so Ctrl-C is noticed even with timeout_s=None
_MAX_DRAIN = 10_000  # bound on messages drained per receive, so a flood cannot spin forever
_MAX_PARTS = 4  # parts of a message kept (one more than a frame has, so that 4 is still a wrong count)
_MAX_INT64 = 2 ** 63 - 1  # MAXMSGSIZE is an int64 in libzmq
_MAX_RCVHWM = 2 ** 31 - 1  # RCVHWM is a C int
_FOREVER_S = 1e15  # a timeout past this (31 million years) is a wait without a deadline


class ClientTimeout(ClientError, TimeoutError):
    """No message arrived within the timeout."""


class ClientHandshakeError(ClientError):
    """The connection cannot carry frames: CURVE on one side only, a wrong server key, or a peer that does not
    speak ZeroMQ. Raised by a receive; libzmq itself would retry in silence for ever."""


_HANDSHAKE_EVENTS = (zmq.EVENT_CONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
                     | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH)
_HANDSHAKE_TRIES = 3  # failures in a row (~0.1 s apart) before they are an error: one can be a publisher stopping


def _server_public_key(key: str | bytes | os.PathLike) -> bytes:
    """A Z85 server public key given as the key itself or as a certificate file (server.key)."""
    try:
        if isinstance(key, bytes) and len(key) == 40:
            return check_z85(key, "the CURVE server key")
        if isinstance(key, str) and len(key) == 40 and not Path(key).exists():
            return check_z85(key.encode("utf-8"), "the CURVE server key")
    except ValueError as exc:
        raise ClientError(str(exc)) from None
    try:
        public, _ = load_certificate(key)
    except Exception as exc:
        why = getattr(exc, "strerror", None) or exc
        raise ClientError(f"cannot read CURVE server public key {key}: {why}") from exc
    return public


def _is_int(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)  # True is an int, not a size


def _check_endpoint(endpoint: str) -> None:
    """libzmq takes a tcp port over 65535 modulo 65536 without a word (99999 connects to 34463), and connects to
    an inproc:// name that only a socket of this Subscriber's own context could bind: a wait for ever."""
    if endpoint.startswith("inproc://"):
        raise ClientError(f"cannot connect to {endpoint}: inproc:// reaches only the same process's ZeroMQ context, "
                          "and edi-live does not publish there; use its tcp://HOST:PORT or ipc:///PATH")
    parts = tcp_parts(endpoint)
    if parts is not None and not (parts[1].isdigit() and 1 <= int(parts[1]) <= 65535):
        raise ClientError(f"cannot connect to {endpoint}: the port must be 1-65535 (tcp://HOST:PORT)")


def _check_timeout(timeout_s: float | None) -> float | None:
    """The timeout as a float, or None (wait) for one beyond any deadline: an int such as 10 ** 400 is past the
    float range, and the deadline's arithmetic raised OverflowError."""
    if timeout_s is not None and not (isinstance(timeout_s, numbers.Real) and not isinstance(timeout_s, bool)
                                      and timeout_s >= 0):  # NaN never ends a wait
        raise ClientError(f"timeout_s must be a number of seconds >= 0, or None to wait (got {timeout_s!r})")
    return None if timeout_s is None or timeout_s > _FOREVER_S else float(timeout_s)


class Subscriber:
    """A SUB socket on one edi-live endpoint (context manager). Frames and stats use separate sockets,
    so waiting for one never consumes the other."""

    def __init__(self, endpoint: str = DEFAULT_ENDPOINT, *, newest_only: bool = True,
                 max_bytes: int = DEFAULT_MAX_BYTES, curve_server_key: str | bytes | os.PathLike | None = None,
                 rcvhwm: int | None = None, stats: bool = True,
                 max_queued_bytes: int = DEFAULT_MAX_QUEUED_BYTES) -> None:
        """rcvhwm: messages queued in libzmq (default 16, or 1000 without newest_only; 0 = as many as
        max_queued_bytes allows), always capped at max_queued_bytes // max_bytes: a subscriber that wants
        every frame of small images lowers max_bytes to get a deeper queue (max_bytes=1 << 20: 1024)."""
        if not (_is_int(max_bytes) and 0 < max_bytes <= _MAX_INT64 and _is_int(max_queued_bytes)
                and max_queued_bytes > 0):
            raise ClientError(f"max_bytes and max_queued_bytes must be positive integers, max_bytes at most 2**63 - 1 "
                              f"(got {max_bytes!r}, {max_queued_bytes!r})")
        if rcvhwm is not None and not _is_int(rcvhwm):
            raise ClientError(f"rcvhwm must be an integer, or None for the default (got {rcvhwm!r})")
        if not isinstance(endpoint, str):
            raise ClientError(f"the endpoint must be a string such as {DEFAULT_ENDPOINT} (got {endpoint!r})")
        _check_endpoint(endpoint)
        self.endpoint = endpoint
        self.newest_only = newest_only
        self.max_bytes = max_bytes = int(max_bytes)
        self.received = 0  # frames handed to the caller
        self.skipped = 0  # frames drained and discarded by newest_only
        self.reconnects = 0  # connections re-established after libzmq dropped them (e.g. an oversized part)
        self._handshake_failures = 0
        self._handshaking: set[zmq.Socket] = set()  # connected, handshake not yet done
        self.last_stats: dict | None = None
        self._server_key = _server_public_key(curve_server_key) if curve_server_key is not None else None
        wanted = int(rcvhwm) if rcvhwm is not None else (16 if newest_only else 1000)
        cap = max(1, int(max_queued_bytes) // max_bytes)
        self.rcvhwm = min(cap if wanted <= 0 else min(wanted, cap), _MAX_RCVHWM)
        self._ctx = zmq.Context(io_threads=1)
        self._monitors: dict[zmq.Socket, zmq.Socket] = {}
        try:
            self._frames = self._socket(wire.FRAME_TOPIC, self.max_bytes, self.rcvhwm)
            self._stats = self._socket(wire.STATS_TOPIC, wire.MAX_HEADER_BYTES, 16) if stats else None
        except BaseException:
            self._ctx.destroy(linger=0)
            raise

    def _socket(self, topic: bytes, max_part: int, rcvhwm: int) -> zmq.Socket:
        sock = self._ctx.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVHWM, rcvhwm)
        sock.setsockopt(zmq.MAXMSGSIZE, max_part)  # a larger part: libzmq drops the connection
        # a vanished publisher host is noticed by TCP keepalive (~8 s), not by ZMTP heartbeats (module doc)
        sock.setsockopt(zmq.TCP_KEEPALIVE, 1)
        sock.setsockopt(zmq.TCP_KEEPALIVE_IDLE, 5)
        sock.setsockopt(zmq.TCP_KEEPALIVE_INTVL, 1)
        sock.setsockopt(zmq.TCP_KEEPALIVE_CNT, 3)
        if self._server_key is not None:
            public, secret = zmq.curve_keypair()
            sock.curve_secretkey, sock.curve_publickey = secret, public
            sock.curve_serverkey = self._server_key
        sock.setsockopt(zmq.SUBSCRIBE, topic)
        sock.setsockopt(zmq.IPV6, int(ipv6_literal(self.endpoint)))  # (without it libzmq retries for ever, unheard)
        try:
            sock.connect(self.endpoint)
        except zmq.ZMQError as exc:
            sock.close(linger=0)
            raise ClientError(f"cannot connect to {self.endpoint}: {exc.strerror}; expected "
                              "tcp://HOST:PORT or ipc:///PATH") from exc
        self._monitors[sock] = sock.get_monitor_socket(zmq.EVENT_DISCONNECTED | _HANDSHAKE_EVENTS)
        return sock

    def _reconnect_if_dropped(self, sock: zmq.Socket) -> None:
        """After libzmq dropped the connection (a part over max_bytes, a protocol error: it does not
        reconnect by itself then), connect again. Harmless after an ordinary disconnect."""
        monitor = self._monitors[sock]
        dropped, failure = False, None
        while monitor.poll(0):
            event = parse_monitor_message(monitor.recv_multipart())
            if event["event"] == zmq.EVENT_CONNECTED:
                self._handshaking.add(sock)
            elif event["event"] == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self._handshaking.discard(sock)
                self._handshake_failures = 0
            elif event["event"] == zmq.EVENT_DISCONNECTED:
                dropped = True
                if sock in self._handshaking:  # closed before a handshake: a peer that is no ZeroMQ publisher
                    self._handshaking.discard(sock)
                    self._handshake_failures += 1
                    failure = failure or 0
            else:  # a failed handshake: libzmq retries it for ever, in silence
                self._handshaking.discard(sock)
                self._handshake_failures += 1
                failure = event["value"]
        if dropped:
            self.reconnects += 1
            try:
                sock.disconnect(self.endpoint)
            except zmq.ZMQError:
                pass  # already gone
            sock.connect(self.endpoint)
        if failure == zmq.PROTOCOL_ERROR_ZMTP_MECHANISM_MISMATCH:  # deterministic: say it at once
            raise ClientHandshakeError(
                f"the publisher at {self.endpoint} does not encrypt: connect without a CURVE server key"
                if self._server_key is not None else f"the publisher at {self.endpoint} encrypts (CURVE): give "
                "its public key (--curve-server-key FILE, curve_server_key=)")
        if failure is not None and self._handshake_failures >= _HANDSHAKE_TRIES:  # not a publisher restarting
            raise ClientHandshakeError(
                f"the encryption handshake with {self.endpoint} keeps failing: that publisher does not encrypt, or "
                "--curve-server-key is not the public key of its --curve-secret-key" if self._server_key is not None
                else f"the handshake with {self.endpoint} keeps failing: it encrypts (CURVE: give its public key "
                "with --curve-server-key), or it does not speak ZeroMQ (edi-live's frames are on --publish, not on "
                "--dv-output)")

    def _wait(self, sock: zmq.Socket, timeout_s: float | None) -> bool:
        timeout_s = _check_timeout(timeout_s)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            slice_s = _SLICE_S if deadline is None else min(_SLICE_S, deadline - time.monotonic())
            if sock.poll(max(0, int(slice_s * 1000))):
                return True
            self._reconnect_if_dropped(sock)
            if deadline is not None and time.monotonic() >= deadline:
                return False

    def _recv_parts(self, sock: zmq.Socket, timeout_s: float | None,
                    newest: bool) -> tuple[list[zmq.Frame] | None, int]:
        """The next message (or the newest available one when `newest`) and how many were skipped."""
        if self._ctx.closed:
            raise ClientError(f"this Subscriber of {self.endpoint} is closed")
        self._reconnect_if_dropped(sock)
        try:  # a message already waiting costs no poll
            parts = self._recv_message(sock, zmq.NOBLOCK)
        except zmq.Again:
            if not self._wait(sock, timeout_s):
                return None, 0
            parts = self._recv_message(sock, 0)
        skipped = 0
        while newest and skipped < _MAX_DRAIN:
            try:
                parts = self._recv_message(sock, zmq.NOBLOCK)
            except zmq.Again:
                break
            except ClientError:  # the messages drained so far and the one in hand are dropped with it: count them
                if sock is self._frames:
                    self.skipped += skipped + 1
                raise
            skipped += 1
        return parts, skipped

    def _recv_message(self, sock: zmq.Socket, flags: int) -> list[zmq.Frame]:
        """One message. libzmq bounds a part's size, not the number of parts: a message of 2 million empty parts
        (4 MB on the wire) made 2 million Python objects (RSS +1.1 GB), so the parts past _MAX_PARTS are received
        and dropped one at a time, and such a message is a ClientError at once (not drained past as old)."""
        parts = [sock.recv(flags, copy=False)]
        count = 1
        while sock.rcvmore:
            part = sock.recv(copy=False)
            count += 1
            if count <= _MAX_PARTS:
                parts.append(part)
        if count > _MAX_PARTS:
            raise ClientError(f"a message of {count} parts arrived from {self.endpoint} (edi-live sends 3 for a "
                              "frame, 2 for stats): not an edi-live publisher?")
        return parts

    def recv(self, timeout_s: float | None = None) -> tuple[dict, np.ndarray] | None:
        """The next frame as (header, image), or None if none arrived within timeout_s (None = wait).

        The image is (h, w) gray or (h, w, 3) BGR (header "layout"), read-only, and shares the message buffer.
        Raises ClientError on a bad message."""
        parts, skipped = self._recv_parts(self._frames, timeout_s, self.newest_only)
        if parts is None:
            return None
        self.skipped += skipped
        header, image = wire.decode_frame(parts, max_bytes=self.max_bytes)
        self.received += 1
        return header, image

    def recv_stats(self, timeout_s: float | None = 0.0) -> dict | None:
        """The newest stats map that arrived since the last call (waiting up to timeout_s), or None."""
        if self._stats is None:
            raise ClientError("this Subscriber was created with stats=False")
        parts, _ = self._recv_parts(self._stats, timeout_s, newest=True)  # only the newest stats matter
        if parts is None:
            return None
        self.last_stats = wire.decode_stats(parts)
        return self.last_stats

    def close(self) -> None:
        """Close the sockets; closing again does nothing (an explicit close() inside `with` is fine)."""
        if self._ctx.closed:
            return
        for sock in self._monitors:
            sock.disable_monitor()
        self._ctx.destroy(linger=0)

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[tuple[dict, np.ndarray]]:
        while True:
            item = self.recv(None)
            if item is not None:
                yield item


def subscribe(endpoint: str = DEFAULT_ENDPOINT, *, newest_only: bool = True, timeout_s: float | None = None,
              max_bytes: int = DEFAULT_MAX_BYTES,
              curve_server_key: str | bytes | os.PathLike | None = None) -> Iterator[tuple[dict, np.ndarray]]:
    """Yield (header, image) for every frame received (the newest one with newest_only).

    timeout_s: the longest wait for one frame; then ClientTimeout is raised (None = wait indefinitely).
    Raises ClientError on a malformed or oversized message. The socket closes when the generator does."""
    with Subscriber(endpoint, newest_only=newest_only, max_bytes=max_bytes,
                    curve_server_key=curve_server_key, stats=False) as sub:
        while True:
            reconnects = sub.reconnects
            item = sub.recv(timeout_s)
            if item is None:
                dropped = sub.reconnects - reconnects
                # libzmq drops the connection at a part over max_bytes, so such frames look like no publisher
                raise ClientTimeout(
                    f"no frame from {endpoint} within {timeout_s} s, and the connection was dropped {dropped} "
                    f"time(s) meanwhile: libzmq drops it at a frame over max_bytes={max_bytes} (raise max_bytes), "
                    "or the publisher restarted" if dropped else
                    f"no frame from {endpoint} within {timeout_s} s: is edi-live running and publishing there?")
            yield item


def _printable(text: str) -> str:
    """A publisher's string as the terminal may show it: control characters (escape sequences) escaped."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def number_arg(kind: type, low: float, high: float | None = None, *, finite: bool = False) -> Callable[[str], Any]:
    """An argparse type: a `kind` number in [low, high] (high None: no upper bound); NaN is refused, and so is
    infinity with `finite`. Also the viewer's (tools/viewer.py)."""

    def parse(text: str) -> Any:
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not low <= value <= (math.inf if high is None else high) or (finite and value == math.inf):
            bound = f"from {low} to {high}" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'} {bound} "
                                             f"(got {text!r})")
        return value

    return parse


def main(argv: list[str] | None = None) -> int:
    """`python -m edi_live.client [ENDPOINT]`: one line per frame received (what edi-live --help promises), until
    --count frames, a --timeout-s without one, or Ctrl-C. Errors are one line; exit 1."""
    import sys

    parser = argparse.ArgumentParser(prog="python -m edi_live.client", description="print the frames an edi-live "
                                     "publisher sends, one line each")
    parser.add_argument("endpoint", nargs="?", default=DEFAULT_ENDPOINT, help=f"default: {DEFAULT_ENDPOINT}")
    parser.add_argument("--curve-server-key", metavar="FILE", help="the publisher's public key (CURVE)")
    parser.add_argument("--count", type=number_arg(int, 0), default=0, metavar="N",
                        help="stop after N frames (default 0: never)")
    parser.add_argument("--timeout-s", type=number_arg(float, 0), default=None, metavar="S",
                        help="give up when no frame arrives for S seconds (default: wait)")
    args = parser.parse_args(argv)
    n = 0
    try:
        for header, image in subscribe(args.endpoint, timeout_s=args.timeout_s,
                                       curve_server_key=args.curve_server_key):
            n += 1
            print(f"seq {header['seq']} t {header['t']} µs {header['kind']} {image.shape[1]}x{image.shape[0]} "
                  f"events {header['n_events']} from {_printable(header['source'])}", flush=True)
            if n == args.count:
                break
    except KeyboardInterrupt:
        pass
    except BrokenPipeError:  # the reader went away ('| head'): done; stdout to devnull, so exit's flush is quiet
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except ClientError as exc:
        print(f"edi-live client: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
