"""A TCP connect that a stop request ends at once, for the DV network input (drivers/dv_network.py).

`socket.create_connection(..., timeout)` blocks for the whole timeout while the peer does not answer (its SYNs are
dropped: a host that is down, a firewall, a listener whose backlog is full), and nothing but the timeout ends it:
a stop (Ctrl-C) waited for it, 5 s by default. Here the connect is non-blocking and polled in short slices, with
the stop event checked between them. The name lookup before it (getaddrinfo) has no timeout and cannot be
interrupted: a resolver that does not answer held a stop for as long as the system's resolver retries (tens of
seconds). It runs on a daemon thread, waited for in the same slices; a lookup abandoned by a stop or the deadline
finishes there on its own, and a connect to the same host and port meanwhile (a reconnect loop) waits for that one
instead of starting another thread that would block as well.
"""

from __future__ import annotations

import errno
import os
import selectors
import socket
import threading
import time

POLL_S = 0.1  # how often a connect in progress looks at the stop event
_CONNECTING = {errno.EINPROGRESS, errno.EALREADY, errno.EWOULDBLOCK}  # connect_ex() of a non-blocking socket


def connect(host: str, port: int, timeout_s: float, stop: threading.Event) -> socket.socket | None:
    """A connected (non-blocking) socket, or None once `stop` is set. Each address of `host` is tried in turn, as
    create_connection() does, under one deadline; the last failure is raised as its OSError subclass
    (ConnectionRefusedError, ...; TimeoutError after `timeout_s`)."""
    deadline = time.monotonic() + timeout_s
    addresses = _resolve(host, port, timeout_s, deadline, stop)
    if addresses is None:
        return None
    error: OSError = OSError(f"no address for {host}")
    for family, kind, proto, _, address in addresses:
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            code = sock.connect_ex(address)
            with selectors.DefaultSelector() as sel:
                sel.register(sock, selectors.EVENT_WRITE)
                while code in _CONNECTING:
                    if stop.is_set():
                        sock.close()
                        return None
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise TimeoutError(errno.ETIMEDOUT, f"no answer within {timeout_s:g} s")
                    if sel.select(min(POLL_S, left)):
                        code = sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
            if code:
                raise OSError(code, os.strerror(code))  # (built as the errno's subclass)
            return sock
        except BaseException as exc:
            sock.close()
            if not isinstance(exc, OSError):
                raise
            error = exc
    raise error


def _resolve(host: str, port: int, timeout_s: float, deadline: float, stop: threading.Event) -> list | None:
    """getaddrinfo(host, port) for a stream socket, or None once `stop` is set; its OSError (socket.gaierror:
    unknown name, ...) is raised here, and TimeoutError if it has not answered by `deadline`."""
    with _LOOKUPS_LOCK:  # a lookup still under way (a connect gave up on it) is waited for, not started again
        lookup = _LOOKUPS.get((host, port))
        if lookup is None:
            lookup = _LOOKUPS[(host, port)] = _Lookup(host, port)
            threading.Thread(target=lookup.run, name=f"name lookup of {host}", daemon=True).start()
    while not lookup.done.wait(max(0.0, min(POLL_S, deadline - time.monotonic()))):
        if stop.is_set():
            return None
        if time.monotonic() >= deadline:
            raise TimeoutError(errno.ETIMEDOUT, f"the name lookup of {host} did not answer within {timeout_s:g} s")
    if stop.is_set():
        return None
    if isinstance(lookup.outcome, UnicodeError):  # not a name the resolver can encode ('a..b', a label > 63)
        reason = lookup.outcome.__cause__ or lookup.outcome  # (the codec's own words: "label empty or too long")
        raise socket.gaierror(socket.EAI_NONAME, f"{host!r} is not a valid host name: {reason}")
    if isinstance(lookup.outcome, Exception):
        raise lookup.outcome
    return lookup.outcome


class _Lookup:
    """One getaddrinfo on its own thread; its result or exception in `outcome` once `done` is set."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.outcome: list | Exception = []
        self.done = threading.Event()

    def run(self) -> None:
        try:
            self.outcome = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)
        except Exception as exc:  # noqa: BLE001 - handed to the waiting connect, raised there
            self.outcome = exc
        finally:
            with _LOOKUPS_LOCK:
                _LOOKUPS.pop((self.host, self.port), None)
            self.done.set()


_LOOKUPS: dict[tuple[str, int], _Lookup] = {}  # the lookups under way
_LOOKUPS_LOCK = threading.Lock()
