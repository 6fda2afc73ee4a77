"""A TCP connect that a stop request ends at once, for the DV network input (drivers/dv_network.py).

`socket.create_connection(..., timeout)` blocks for the whole timeout while the peer does not answer (its SYNs are
dropped: a host that is down, a firewall, a listener whose backlog is full), and nothing but the timeout ends it:
a stop (Ctrl-C) waited for it, 5 s by default. Here the connect is non-blocking and polled in short slices, with
the stop event checked between them. The name lookup before it (getaddrinfo) has no timeout and cannot be
interrupted: a resolver that does not answer held a stop for as long as the system's resolver retries (tens of
seconds). It runs on a daemon thread, waited for in the same slices; a lookup abandoned by a stop or the deadline
finishes there on its own.
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
    outcome: list = []
    done = threading.Event()

    def lookup() -> None:
        try:
            outcome.append(socket.getaddrinfo(host, port, type=socket.SOCK_STREAM))
        except OSError as exc:
            outcome.append(exc)
        finally:
            done.set()

    threading.Thread(target=lookup, name=f"name lookup of {host}", daemon=True).start()
    while not done.wait(max(0.0, min(POLL_S, deadline - time.monotonic()))):
        if stop.is_set():
            return None
        if time.monotonic() >= deadline:
            raise TimeoutError(errno.ETIMEDOUT, f"the name lookup of {host} did not answer within {timeout_s:g} s")
    if stop.is_set():
        return None
    if isinstance(outcome[0], OSError):
        raise outcome[0]
    return outcome[0]
