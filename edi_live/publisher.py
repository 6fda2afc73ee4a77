"""The publisher thread: owns the ZeroMQ context and PUB socket(s) and sends frames and once-a-second stats.

The worker hands reconstructions to `submit()`, which never blocks. When nothing is queued and the socket is
free, submit() encodes and sends the frame right away on the caller's thread (NOBLOCK: a few tens of µs, no
thread hand-over); otherwise the frame goes to a bounded inbox that the thread drains, which drops its oldest
entry when full (counted). One lock serialises the socket between the two threads and keeps frames in
submit order. Sends use NOBLOCK and `copy=False`; `SNDHWM` bounds libzmq's per-subscriber
queue, and PUB drops for a subscriber that does not read, so a slow or dead viewer never slows the worker and
memory stays bounded. Bind failures surface synchronously from `start()` as `BindError`.

CURVE: `curve_secret_key` is the path of a ZeroMQ certificate file holding the server's secret key, in the
ZPL format written by `zmq.auth.create_certificates` (a `*.key_secret` file with `public-key` and
`secret-key` in Z85). Generate a pair with ``python -m edi_live.publisher --gen-curve-keys DIR``; subscribers
need only `DIR/server.key` (the public half). Clients are not authenticated: CURVE here gives encryption and
server authentication, any subscriber that knows the server's public key may connect.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zmq
import zmq.auth

from edi_live import wire
from edi_live.console import print_lines
from edi_live.curve_keys import load_secret_key
from edi_live.datatypes import Reconstruction
from edi_live.errors import OutputError, PublishError
from edi_live.stats import LatencySamples
from edi_live.subscriptions import Subscriptions
from edi_live.zmq_bind import bind

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp://127.0.0.1:5555"
DEFAULT_SNDHWM = 16  # frames queued per subscriber inside libzmq before PUB drops for that subscriber
DEFAULT_INBOX = 64  # reconstructions waiting for the thread; a publisher that keeps up never fills it
HEARTBEAT_IVL_MS, HEARTBEAT_TIMEOUT_MS = 1000, 3000
MAX_INBOUND_BYTES = 4096  # what a subscriber sends is subscriptions: a topic prefix each
LATENCY_SAMPLES = 8192  # bound on latency samples kept per stats interval (the most recent win)
_START_TIMEOUT_S = 10.0
_NOBLOCK = int(zmq.NOBLOCK)
_MORE = int(zmq.NOBLOCK | zmq.SNDMORE)
_POLLIN, _EVENTS = int(zmq.POLLIN), int(zmq.EVENTS)
_send = zmq.backend.Socket.send  # the sugar layer's send adds ~0.2 µs a part of checks a frame does not need


def generate_curve_keys(directory: str | os.PathLike) -> tuple[Path, Path]:
    """Write `server.key` (public, for subscribers) and `server.key_secret` (for the publisher) into directory;
    PublishError if it already holds either, or cannot be written."""
    if not os.fspath(directory):  # Path("") is ".": an unset shell variable would put the secret key here
        raise PublishError("--gen-curve-keys needs a folder, not an empty path")
    directory = Path(directory)
    taken = [p.name for p in (directory / "server.key", directory / "server.key_secret") if p.exists()]
    if taken:  # its subscribers hold the public key: a new pair would lock them out, and the old secret be lost
        raise PublishError(f"{directory} already holds a key pair ({taken[0]}), which is never replaced: remove "
                           "it or choose another folder")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        public, secret = zmq.auth.create_certificates(directory, "server")
        os.chmod(secret, 0o600)
    except OSError as exc:
        raise PublishError(f"cannot write the keys into {directory}: {exc.strerror or exc}") from exc
    return Path(public), Path(secret)


class Publisher:
    """Sends reconstructions over ZeroMQ PUB sockets from its own thread.

    endpoints: ZeroMQ endpoints to bind (``tcp://127.0.0.1:*`` picks a free port; see `bound_endpoints`).
    source: camera name or serial, put in every frame header.
    stats_provider: called once per stats interval on the publisher thread; its map is merged with the
    publisher's own counters (frames_sent, publish_dropped, latency_p50_us, latency_p99_us) into the stats
    message. on_error: called with the exception if the thread dies (the node's fail()).
    """

    def __init__(self, endpoints: Sequence[str] | str = (DEFAULT_ENDPOINT,), source: str = "unknown", *,
                 curve_secret_key: str | os.PathLike | None = None, sndhwm: int = DEFAULT_SNDHWM,
                 inbox_size: int = DEFAULT_INBOX, stats_provider: Callable[[], dict] | None = None,
                 stats_interval_s: float = 1.0,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        if isinstance(endpoints, str):
            endpoints = [endpoints]
        if not endpoints:
            raise PublishError("Publisher needs at least one endpoint (e.g. tcp://127.0.0.1:5555)")
        if inbox_size < 1 or sndhwm < 0 or stats_interval_s <= 0:
            raise PublishError(f"invalid publisher limits (got inbox_size={inbox_size}, sndhwm={sndhwm}, "
                               f"stats_interval_s={stats_interval_s})")
        self.endpoints = list(endpoints)
        self.source = source
        self.curve_secret_key = curve_secret_key
        self.sndhwm = sndhwm
        self.stats_interval_s = stats_interval_s
        self.bound_endpoints: list[str] = []
        self.curve_public_key: bytes | None = None
        self._stats_provider = stats_provider
        self._on_error = on_error
        self._inbox: collections.deque[Reconstruction] = collections.deque()
        self._inbox_size = inbox_size
        self._cond = threading.Condition()
        # the socket is used by the publisher thread and, through submit(), by the caller's thread: one at a time
        self._sock_lock = threading.Lock()
        self._sock: zmq.Socket | None = None
        self._stop = False
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self.error: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._latency = LatencySamples(LATENCY_SAMPLES)
        self._seq = 0
        self._sent = 0
        self._dropped_inbox = 0
        self._dropped_socket = 0
        self._unsubscribed = 0  # frames not encoded: no subscriber to "frame" at the time
        self._encoder = wire.FrameEncoder(source)
        self._subscriptions = Subscriptions(wire.FRAME_TOPIC)
        self._stats: dict[str, Any] = {"latency_p50_us": None, "latency_p99_us": None, "sent_per_s": 0.0}
        self._provider_failed = False

    # ---- called from other threads ----

    def start(self) -> None:
        """Start the thread and bind every endpoint; raises BindError (or PublishError) if that fails."""
        if self._thread is not None:
            raise PublishError("Publisher.start() called twice")
        self._thread = threading.Thread(target=self._run, name="publisher", daemon=True)
        self._thread.start()
        if not self._ready.wait(_START_TIMEOUT_S):
            raise PublishError(f"publisher did not bind {self.endpoints} within {_START_TIMEOUT_S:.0f} s")
        if self._start_error is not None:
            self._thread.join(_START_TIMEOUT_S)
            raise self._start_error

    def submit(self, rec: Reconstruction) -> None:
        """Send one reconstruction, or queue it for the thread. Never waits: when the inbox is empty and the
        socket is free, the frame is encoded and sent (NOBLOCK) right here on the caller's thread, which saves
        a thread hand-over per frame; otherwise it is queued, and a full inbox drops its oldest entry (counted)."""
        if not self._inbox and self._sock_lock.acquire(blocking=False):
            try:
                # the thread holds _sock_lock while it takes and sends a batch, so an empty inbox seen under the
                # lock means nothing submitted earlier is still unsent: frame order is kept
                if self._sock is not None and not self._inbox:
                    try:
                        self._send_frame(self._sock, rec)
                    except zmq.ZMQError as exc:  # a socket failure is the publisher's, as on its own thread
                        self._fail(exc)
                    return
            finally:
                self._sock_lock.release()
        with self._cond:
            if len(self._inbox) >= self._inbox_size:
                self._inbox.popleft()
                self._dropped_inbox += 1
            self._inbox.append(rec)
            self._cond.notify()

    def wants_frames(self) -> bool:
        """Whether anyone subscribes to frames now (for the worker: a frame nobody wants need not be rendered).
        Reads the subscriptions that arrived when the socket is free; never waits."""
        if self._sock_lock.acquire(blocking=False):
            try:
                if self._sock is not None:
                    return self._frames_wanted(self._sock)
            finally:
                self._sock_lock.release()
        return self._subscriptions.wanted

    def pending(self) -> int:
        """Reconstructions waiting in the inbox (never more than inbox_size)."""
        return len(self._inbox)

    def stats(self) -> dict[str, Any]:
        """Counters in code names: sent; dropped = dropped_inbox + dropped_socket (the latter also counts
        frames the wire cannot carry); unsubscribed (frames not sent because nobody subscribed to frames);
        latency_p50_us and latency_p99_us of the last stats interval (None when no frame was sent in it);
        sent_per_s; last_seq."""
        return {"sent": self._sent, "dropped": self._dropped_inbox + self._dropped_socket,
                "dropped_inbox": self._dropped_inbox, "dropped_socket": self._dropped_socket,
                "unsubscribed": self._unsubscribed,
                "last_seq": self._seq - 1, **self._stats}

    def close(self, timeout_s: float = 2.0) -> None:
        """Send what the inbox holds, close the sockets with linger 0 and join the thread."""
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise PublishError(f"publisher thread did not stop within {timeout_s} s")

    def __enter__(self) -> Publisher:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- the publisher thread ----

    def _open(self, ctx: zmq.Context) -> zmq.Socket:
        sock = ctx.socket(zmq.XPUB)  # a PUB that also tells whether anyone subscribes (Subscriptions)
        try:
            self._configure(sock)
        except BaseException:
            sock.close(linger=0)
            raise
        return sock

    def _configure(self, sock: zmq.Socket) -> None:
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.SNDHWM, self.sndhwm)
        # ZMTP heartbeats: a subscriber whose host vanished (half-open TCP) is dropped with its queue
        sock.setsockopt(zmq.HEARTBEAT_IVL, HEARTBEAT_IVL_MS)
        sock.setsockopt(zmq.HEARTBEAT_TIMEOUT, HEARTBEAT_TIMEOUT_MS)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_INBOUND_BYTES)  # a peer sending more is disconnected by libzmq
        if self.curve_secret_key is not None:
            if not zmq.has("curve"):
                raise PublishError("this libzmq was built without CURVE; cannot use --curve-secret-key")
            public, secret = load_secret_key(self.curve_secret_key)
            sock.curve_secretkey = secret
            sock.curve_publickey = public
            sock.curve_server = True
            self.curve_public_key = public
        for endpoint in self.endpoints:
            self.bound_endpoints.append(bind(sock, endpoint))

    def _run(self) -> None:
        ctx = zmq.Context(io_threads=1)
        sock = None
        try:
            try:
                sock = self._open(ctx)
            except BaseException as exc:
                self._start_error = exc
                return
            finally:
                self._ready.set()
            self._loop(sock)
        except BaseException as exc:  # anything after start is fatal to the node: hand it on
            self._fail(exc)
        finally:
            with self._sock_lock:
                self._sock = None  # submit() queues from now on (nothing will send it: counted below)
            if sock is not None:
                sock.close(linger=0)
            ctx.term()

    def _fail(self, exc: BaseException) -> None:
        if self.error is None:
            self.error = exc
        log.error("publisher failed: %s", exc)
        if self._on_error is not None:
            self._on_error(exc)

    def _loop(self, sock: zmq.Socket) -> None:
        interval_ns = int(self.stats_interval_s * 1e9)
        next_stats_ns = time.monotonic_ns() + interval_ns
        sent_at_last_stats = 0
        with self._sock_lock:
            self._sock = sock
        while True:
            with self._cond:
                if not self._inbox and not self._stop:
                    self._cond.wait(max(0.0, (next_stats_ns - time.monotonic_ns()) / 1e9))
                stopping = self._stop
            with self._sock_lock:  # taken before the inbox is emptied: see submit()
                with self._cond:
                    batch = list(self._inbox)
                    self._inbox.clear()
                for rec in batch:
                    self._send_frame(sock, rec)
            now_ns = time.monotonic_ns()
            if now_ns >= next_stats_ns:
                # the node's stats are gathered without the socket lock: frames keep going out inline meanwhile
                provided = self._provided_stats()
                with self._sock_lock:
                    elapsed_s = (now_ns - next_stats_ns + interval_ns) / 1e9
                    self._stats["sent_per_s"] = (self._sent - sent_at_last_stats) / elapsed_s
                    sent_at_last_stats = self._sent
                    self._send_stats(sock, provided)
                next_stats_ns = now_ns + interval_ns
            if stopping:
                with self._sock_lock:
                    # frames submitted since the last drain were queued: send them before the socket goes
                    with self._cond:
                        batch = list(self._inbox)
                        self._inbox.clear()
                    for rec in batch:
                        self._send_frame(sock, rec)
                    self._sock = None
                return

    def _frames_wanted(self, sock: zmq.Socket) -> bool:
        subscriptions = self._subscriptions
        if subscriptions.check_due():
            while sock.getsockopt(_EVENTS) & _POLLIN:
                subscriptions.apply(sock.recv(_NOBLOCK))
        return subscriptions.wanted

    def _send_frame(self, sock: zmq.Socket, rec: Reconstruction) -> None:
        if not self._frames_wanted(sock):
            self._unsubscribed += 1
            return
        try:
            parts = self._encoder.encode(rec, self._seq)
        except ValueError as exc:  # a reconstruction the wire cannot carry is a bug upstream; count it
            self._dropped_socket += 1
            log.warning("frame not published: %s", exc)
            return
        self._seq += 1
        try:
            # part by part with int flags: send_multipart's per-call checks and enum arithmetic cost a few µs a
            # frame. Every part is copied into its message, the pixels too: pyzmq's zero-copy send releases the
            # buffer through its garbage-collector thread, which cost more than the copy at 346x260 (90 kB:
            # 67 against 51 µs a frame with a subscriber; under 64 kB pyzmq copied anyway). XPUB does not
            # block: with NOBLOCK a message over SNDHWM is dropped whole.
            last = len(parts) - 1
            for i, part in enumerate(parts):
                _send(sock, part, _MORE if i < last else _NOBLOCK)
        except zmq.Again:
            self._dropped_socket += 1
            return
        self._sent += 1
        if rec.arrival_ns > 0:
            self._latency.add((time.monotonic_ns() - rec.arrival_ns) / 1e3)

    def _provided_stats(self) -> dict[str, Any]:
        if self._stats_provider is None:
            return {}
        try:
            return dict(self._stats_provider())
        except Exception as exc:  # stats must not stop frames; say it once
            if not self._provider_failed:
                log.warning("stats provider failed (%s: %s); publishing own counters only",
                            type(exc).__name__, exc)
                self._provider_failed = True
            return {}

    def _send_stats(self, sock: zmq.Socket, provided: dict[str, Any]) -> None:
        p50, p99 = self._latency.take()
        self._stats["latency_p50_us"], self._stats["latency_p99_us"] = p50, p99
        merged: dict[str, Any] = dict(provided)
        own = self.stats()
        if "frames_per_s" not in merged:
            merged["frames_per_s"] = own["sent_per_s"]
        merged.update(own)
        merged.setdefault("source", self.source)
        try:
            sock.send_multipart(wire.encode_stats(merged), flags=zmq.NOBLOCK)
        except zmq.Again:
            pass  # stats are resent next second


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m edi_live.publisher",
        description="Publisher utilities. Generate a CURVE key pair for `edi-live --curve-secret-key`.",
        epilog="example: python -m edi_live.publisher --gen-curve-keys ~/.config/edi-live/curve\n"
               "  then: edi-live --replay rec.aedat4 --curve-secret-key ~/.config/edi-live/curve/server.key_secret\n"
               "  and:  python -m edi_live.client --curve-server-key ~/.config/edi-live/curve/server.key",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gen-curve-keys", metavar="DIR", required=True,
                        help="write server.key (public, give to subscribers) and server.key_secret (keep private)")
    args = parser.parse_args(argv)
    try:
        public, secret = generate_curve_keys(args.gen_curve_keys)
        print_lines([f"public key (for subscribers): {public}",
                     f"secret key (for edi-live --curve-secret-key): {secret}"])
    except (PublishError, OutputError) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
