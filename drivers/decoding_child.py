"""Decoding a recording in a child process, so the node's own process only receives ready packets.

Owns: the child process that runs `drivers.replay_merge.merged_packets` (decompression, FlatBuffers walk, merge and slicing) pass after
pass, and the socket pair that carries its packets back in order. Why: that work comes in bursts (one file packet
of ~20k events at a time, ~0.5 ms of CPU in a few long C calls that hold the GIL). In the node's process it made
the worker wait for the GIL right when a packet had arrived: the slowest 1 % of latent frames at 1 M events/s
paced replay took 2 ms instead of 0.75 ms. In a child the burst only costs CPU on another core, and receiving a
packet costs one `recv_into` of its events straight into their array (a pickled multiprocessing Pipe cost 2-3
copies and made the node's pump 0.18 s per 11 M events instead of 0.10 s).

Messages (child -> parent): a 16-byte header (sizes), a pickled tuple, then for a packet its events as raw bytes.
The tuples: ("packet", Packet without events) | ("pass", t_first, t_last) at the end of each pass over the file |
("error", message, path, offset) for a RecordingError (after every packet before the defect) | ("crash", text,
traceback) for anything else | ("end",).

The child is started through a forkserver (spawn where there is none), which imports the parent's main module
again as "__mp_main__": that module must not start work at import (the CLI's does not). The server also imports
`drivers._forkserver_warmup`, which calls `warm_decoder()` there once, so every child is forked with the AEDAT4
reader's numba kernels loaded (a child that loads them itself needs ~0.4 s for its first packet). The parent closes its end
to stop the child. The child ignores SIGINT, SIGTERM and SIGHUP, so Ctrl-C in a terminal (or a signal to the process
group) stops only the node, which then stops the child. Those signals are blocked while the server or a child is
started (`_stop_signals_held`), so that one arriving before the new process ignores them cannot kill it.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import logging
import multiprocessing as mp
import multiprocessing.util  # noqa: F401 - registers its exit handler before ours (ours must run first)
import os
import pickle
import select
import signal
import socket
import struct
import tempfile
import traceback
import weakref
from typing import Any, Iterator

import numpy as np

from drivers.replay_merge import merged_packets, next_pass_offset
from edi_live.aedat4 import Aedat4Writer
from edi_live.datatypes import EVENT_DTYPE, Packet, empty_imu, empty_triggers
from edi_live.errors import RecordingError, SourceError

log = logging.getLogger(__name__)

_JOIN_S = 2.0
_HEAD = struct.Struct("<QQ")  # bytes of the pickled message, bytes of raw events after it
_SOCK_BUF = 4 << 20
_NICE = 5  # the child only reads ahead: when a core is contended, the node's threads go first
_MIN_FREE_FDS = 16  # under fewer (ulimit -n), multiprocessing's forkserver fails and prints its own traceback


def _context() -> Any:
    # forkserver: a child forked from a clean server (no threads, no ZeroMQ context); the node's process itself
    # must not fork (it runs threads). The server preloads the decoder with its numba kernels (start_early).
    methods = mp.get_all_start_methods()
    ctx = mp.get_context("forkserver" if "forkserver" in methods else "spawn")
    if ctx.get_start_method() == "forkserver":
        ctx.set_forkserver_preload(["drivers.decoding_child", "drivers._forkserver_warmup"])
    return ctx


def warm_decoder() -> None:
    """Write a tiny recording to a temporary file and decode it once, so the AEDAT4 reader's numba kernels are
    loaded in this process (compiled if the on-disk cache is cold). The file is always removed.

    Raises SourceError naming the cause if that fails; callers that can run without it report it and go on.
    """
    events = np.zeros(8, EVENT_DTYPE)
    events["t"] = np.arange(8)
    try:
        with tempfile.TemporaryDirectory(prefix="edi-live-warm-") as tmp:
            path = os.path.join(tmp, "warm.aedat4")
            with Aedat4Writer(path, 4, 4) as writer:
                writer.write_events(events)
            decoded = sum(len(p.events) for p in merged_packets(path))
    except Exception as exc:  # noqa: BLE001 - any failure, bug or environment, becomes one reported error
        raise SourceError(f"warming up the AEDAT4 decoder failed: {type(exc).__name__}: {exc}") from exc
    if decoded != len(events):
        raise SourceError(f"warming up the AEDAT4 decoder failed: it decoded {decoded} of {len(events)} events")


def warm_decoder_or_warn() -> bool:
    """`warm_decoder()`, logging a warning instead of raising: without it, each child only starts slower."""
    try:
        warm_decoder()
    except SourceError as exc:
        log.warning("%s; each decoding process loads the decoder itself (its first packet comes ~0.4 s later)", exc)
        return False
    return True


def start_early() -> None:
    """Start the forkserver now, in the background: it loads the decoder's kernels while the caller does its own
    warm-up, so the first child's first packet comes in milliseconds instead of ~0.4 s. Optional and harmless to
    repeat. A server that cannot start now is not an error yet: DecodeProcess reports it when a child is needed
    (and the replay then decodes in its own process)."""
    ctx = _context()
    if ctx.get_start_method() != "forkserver":
        return
    try:
        from multiprocessing import forkserver

        with _stop_signals_held():
            forkserver.ensure_running()
    except (OSError, ValueError) as exc:
        log.debug("the decoding forkserver did not start early (%s); DecodeProcess will report it", exc)


class _ParentGone(Exception):
    """The parent closed its end (it stopped reading): the child just ends."""


class _Sender:
    """The child's end: one message = a header, the pickled tuple, then a packet's events as raw bytes."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock

    def send(self, message: tuple) -> None:
        raw = b""
        if message[0] == "packet":
            packet = message[1]
            raw = np.ascontiguousarray(packet.events).view(np.uint8).data
            packet.events = None
            # empty structured arrays cost ~7 µs per packet to unpickle (their dtype): sent as None
            packet.imu = packet.imu if len(packet.imu) else None
            packet.triggers = packet.triggers if len(packet.triggers) else None
        meta = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        try:
            self.sock.sendall(_HEAD.pack(len(meta), len(raw)) + meta)
            if len(raw):
                self.sock.sendall(raw)
        except OSError as exc:  # EPIPE, ECONNRESET: not to be confused with an OSError reading the file
            raise _ParentGone() from exc

    def close(self) -> None:
        self.sock.close()


# the node's stop signals (edi_live.stop_signals): the node stops this child itself, after it stopped reading
_STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextlib.contextmanager
def _stop_signals_held() -> Iterator[None]:
    """Block the stop signals in the calling thread while it starts a process, which inherits the mask (through
    exec too). The forkserver ignores SIGINT only after importing its preload (~0.5 s of numba), and a child only
    once `_child` runs: a Ctrl-C to the whole group before that killed them, printing a KeyboardInterrupt
    traceback on the node's stderr. Here the signals stay pending and arrive when the block ends.

    multiprocessing's resource tracker, which the forkserver starts first, unblocks SIGINT and SIGTERM after
    starting itself (it blocks them around its own start): it is started before the block, so it leaves it."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    before = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _child(conn: Any, path: str, max_packet_us: int, loop: bool, size: tuple[int, int] | None = None) -> None:
    """Child process: every pass's packets into the socket `conn`, in order, until the parent goes away."""
    conn = _Sender(conn)
    for sig in _STOP_SIGNALS:  # Ctrl-C / kill / hang-up of the whole group: the node stops us itself
        signal.signal(sig, signal.SIG_IGN)
    # no log lines from here: the parent's own reader announced what the header says, and our faults travel to
    # the parent as messages (unformatted lines from this process would interleave with the node's)
    logging.disable(logging.WARNING)
    try:
        os.nice(_NICE)
    except OSError:
        pass
    offset = 0
    try:
        while True:
            span: dict = {}
            produced = False
            for packet in merged_packets(path, time_offset_us=offset, max_packet_us=max_packet_us, span=span,
                                         size=size):
                produced = True
                conn.send(("packet", packet))
            if "t_first" not in span:
                break
            conn.send(("pass", span["t_first"], span["t_last"]))
            if not (loop and produced):
                break
            offset = next_pass_offset(offset, span)
        conn.send(("end",))
    except RecordingError as exc:
        _send_quietly(conn, ("error", _message(exc), exc.path, exc.offset))
    except _ParentGone:
        pass  # the parent stopped reading: nothing left to do
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it as one line
        _send_quietly(conn, ("crash", f"{type(exc).__name__}: {exc}", traceback.format_exc()))
    finally:
        conn.close()


def _message(exc: RecordingError) -> str:
    """The message without the "path at byte N: " prefix that RecordingError adds (it is added again)."""
    text = str(exc)
    if exc.path is not None:
        where = f"{exc.path}" + (f" at byte {exc.offset}" if exc.offset is not None else "") + ": "
        if text.startswith(where):
            return text[len(where):]
    return text


def _send_quietly(conn: _Sender, message: tuple) -> None:
    try:
        conn.send(message)
    except _ParentGone:
        pass


def _check_free_descriptors() -> None:
    """OSError (the replay then decodes in its own process) when too few file descriptors are free to start a child:
    the forkserver would fail receiving them and print a traceback of its own (seen under ulimit -n 14-20)."""
    import resource

    soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    try:
        free = soft - len(os.listdir("/proc/self/fd")) if soft != resource.RLIM_INFINITY else None
    except OSError:  # no /proc (not Linux): nothing to check against
        free = None
    if free is not None and free < _MIN_FREE_FDS:
        raise OSError(errno.EMFILE, f"only {free} file descriptors free under 'ulimit -n {soft}', a decoding process "
                                    f"needs {_MIN_FREE_FDS}")


class DecodeProcess:
    """Iterates the packets a child process decodes from `path` (see the module docstring).

    `next_packet(timeout_s)` returns a Packet, None when nothing came within timeout_s, and raises StopIteration
    at the end. `passes` holds (t_first, t_last) of each finished pass. `close()` stops the child (idempotent).
    `size` (width, height): the sensor every pass must have (merged_packets).
    """

    def __init__(self, path: str, max_packet_us: int, loop: bool, size: tuple[int, int] | None = None) -> None:
        _check_free_descriptors()
        ctx = _context()
        self._sock, child_sock = socket.socketpair()
        for sk, opt in ((self._sock, socket.SO_RCVBUF), (child_sock, socket.SO_SNDBUF)):
            sk.setsockopt(socket.SOL_SOCKET, opt, _SOCK_BUF)
        self._proc = ctx.Process(target=_child, args=(child_sock, path, max_packet_us, loop, size),
                                 name="edi-live-decode", daemon=True)
        try:
            with _stop_signals_held():
                self._proc.start()
        except BaseException:
            self._sock.close()
            raise
        finally:
            child_sock.close()  # the child has its own copy: EOF once the child exits
        self._head = bytearray(_HEAD.size)
        self.path = path
        self.passes: list[tuple[int, int]] = []
        self._ended = False
        _LIVE.add(self)

    def _recv_into(self, view: memoryview) -> None:
        got = 0
        while got < len(view):
            n = self._sock.recv_into(view[got:])
            if n == 0:
                raise EOFError("end of stream")
            got += n

    def _recv(self, timeout_s: float) -> tuple | None:
        if not select.select([self._sock], [], [], timeout_s)[0]:
            return None
        self._recv_into(memoryview(self._head))
        n_meta, n_raw = _HEAD.unpack(self._head)
        meta = bytearray(n_meta)
        self._recv_into(memoryview(meta))
        message = pickle.loads(meta)
        if message[0] == "packet":
            events = np.empty(n_raw // EVENT_DTYPE.itemsize, EVENT_DTYPE)
            if n_raw:
                self._recv_into(memoryview(events.view(np.uint8)))
            message[1].events = events
            if message[1].imu is None:
                message[1].imu = empty_imu()
            if message[1].triggers is None:
                message[1].triggers = empty_triggers()
        return message

    def next_packet(self, timeout_s: float) -> Packet | None:
        while not self._ended:
            try:
                message = self._recv(timeout_s)
                if message is None:
                    return None
            except (EOFError, OSError):  # the child died (killed, out of memory), perhaps mid-message
                self._ended = True
                self._proc.join(_JOIN_S)
                raise SourceError(f"{self.path}: the decoding process ended unexpectedly "
                                  f"(exit code {self._proc.exitcode})") from None
            kind = message[0]
            if kind == "packet":
                return message[1]
            if kind == "pass":
                self.passes.append((message[1], message[2]))
                continue
            self._ended = True
            if kind == "error":
                raise RecordingError(message[1], message[2], message[3])
            if kind == "crash":  # a bug, not a bad file: its traceback is in the debug log
                log.debug("the decoding process failed:\n%s", message[2])
                raise SourceError(f"{self.path}: decoding failed: {message[1]}")
        raise StopIteration

    def __iter__(self) -> Iterator[Packet]:
        while True:
            try:
                packet = self.next_packet(1.0)
            except StopIteration:
                return
            if packet is not None:
                yield packet

    def close(self) -> None:
        _LIVE.discard(self)
        self._ended = True
        self._sock.close()  # the child's next send fails and it exits
        self._proc.join(_JOIN_S)
        if self._proc.is_alive():
            self._proc.kill()  # it ignores SIGTERM
            self._proc.join(_JOIN_S)


_LIVE: "weakref.WeakSet[DecodeProcess]" = weakref.WeakSet()


@atexit.register
def _close_all() -> None:
    """At interpreter exit, stop children nobody closed (an abandoned iterator). The child ignores SIGTERM, so
    multiprocessing's own exit handler, which terminates and then joins daemon children, would wait forever on
    a child blocked writing to our still-open pipe."""
    for child in list(_LIVE):
        child.close()
