"""Binding the publisher's ZeroMQ socket to one endpoint, and saying in one line why a bind failed.

Owns two cases libzmq gets wrong for a node run as a service: an IPv6 address (`tcp://[::1]:5555`) is refused as
"no such device" unless the socket has ZMQ_IPV6 set, so it is set for such an endpoint; and an `ipc://PATH`
that another live process (a second edi-live) serves is taken over without an error, since libzmq unlinks the
path before it binds: the first node's subscribers and every later one then silently reach the second. A path
nobody answers on (left by a node that was killed) is reused.
"""

from __future__ import annotations

import errno
import os
import socket
import stat

import zmq

from edi_live.checks import ipv6_literal
from edi_live.errors import BindError


def bind(sock: zmq.Socket, endpoint: str) -> str:
    """Bind `sock` to `endpoint`; the endpoint actually bound (a `*` port resolved). BindError on failure."""
    scheme, _, address = endpoint.partition("://")
    # per bind (libzmq reads the option then): on for an IPv6 address only, so that an IPv4 endpoint is bound,
    # and reported in the log, as the IPv4 address it names rather than as ::ffff:127.0.0.1
    sock.setsockopt(zmq.IPV6, int(ipv6_literal(endpoint)))
    if scheme == "ipc" and _served(address):
        raise BindError(f"cannot publish on {endpoint}: another process (another edi-live?) is publishing there "
                        "already; stop it or choose another path")
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        raise BindError(bind_message(endpoint, exc)) from exc
    return sock.getsockopt_string(zmq.LAST_ENDPOINT)


def _served(path: str) -> bool:
    """Whether a process accepts connections on the Unix socket at `path` (not on Linux's abstract names, '@')."""
    if path.startswith("@"):
        return False
    try:
        if not stat.S_ISSOCK(os.lstat(path).st_mode):
            return False
    except OSError:
        return False
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        probe.settimeout(1.0)
        probe.connect(path)
    except OSError:  # ECONNREFUSED: a socket file nobody listens on any more
        return False
    finally:
        probe.close()
    return True


def bind_message(endpoint: str, exc: zmq.ZMQError) -> str:
    """The one line for a failed bind of `endpoint`."""
    if exc.errno == zmq.EADDRINUSE:
        return (f"cannot publish on {endpoint}: address already in use (another edi-live or program holds "
                "that port); choose another with --publish tcp://127.0.0.1:PORT")
    if exc.errno in (zmq.EADDRNOTAVAIL, errno.ENODEV):  # ENODEV: a host name that does not resolve (an interface?)
        return (f"cannot publish on {endpoint}: this machine has no such address or network interface; use "
                "127.0.0.1 or 0.0.0.0")
    if exc.errno in (zmq.EINVAL, zmq.EPROTONOSUPPORT):
        return (f"cannot publish on {endpoint}: not a valid ZeroMQ endpoint ({exc.strerror}); expected "
                "tcp://HOST:PORT or ipc:///PATH")
    return f"cannot publish on {endpoint}: {exc.strerror}"
