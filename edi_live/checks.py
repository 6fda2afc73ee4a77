"""Value checks for the configuration, each failing with a one-line `ConfigError` that names the option and the
bad value "(got ...)": integer and positive-number ranges, ZeroMQ and DV network endpoints, and sizes against
the memory the system can still give. No I/O beyond reading /proc/meminfo.
"""

from __future__ import annotations

import math
import os
import stat
from typing import Any

from edi_live.errors import ConfigError


def check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


def int_in(name: str, value: Any, lo: int, hi: int, what: str) -> None:
    """An int (not a bool) in [lo, hi]; `what` says what it counts, for the message."""
    hi_text = f"10^{len(str(hi)) - 1}" if str(hi).rstrip("0") == "1" else str(hi)
    check(isinstance(value, int) and not isinstance(value, bool) and lo <= value <= hi,
          f"{name} must be an integer in [{lo}, {hi_text}] ({what}) (got {value!r})")


def finite_number(value: Any) -> bool:
    """An int or float (not a bool) with a finite float value (an integer beyond a float's range is not)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


MAX_WAIT_S = 10**9
"""The longest period (s) an option may set for the node's threads to wait out (~31 years): beyond it a wait
overflows (threading.TIMEOUT_MAX is ~9.2e9 s) and so does a period in µs once it is infinite as a float."""


def positive_or_none(name: str, value: float | None, *, wait: bool = False) -> None:
    """A positive finite number, or None; `wait`: also at most MAX_WAIT_S (a period the node waits out)."""
    if value is not None:
        limit = " of at most 10^9 s" if wait else ""
        check(finite_number(value) and value > 0 and (not wait or value <= MAX_WAIT_S),
              f"{name} must be a positive number{limit} (got {value!r})")


def available_memory_bytes() -> int | None:
    """Memory the system can still give (Linux MemAvailable, else the physical total), or None if unknown."""
    try:
        with open("/proc/meminfo", "rb") as fh:
            for line in fh:
                if line.startswith(b"MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def fits_memory(name: str, count: int, item_bytes: int, default: str) -> None:
    """`count` items of `item_bytes` each must fit in the available memory (checked before allocating)."""
    need, free = count * item_bytes, available_memory_bytes()
    check(free is None or need <= free,
          f"{name} {count} needs {need / 2**30:.1f} GiB ({item_bytes} bytes each) but only {(free or 0) / 2**30:.1f} "
          f"GiB of memory is available; choose at most {(free or 0) // item_bytes} (default {default})")


def check_endpoint(endpoint: Any) -> None:
    """A ZeroMQ bind endpoint: SCHEME://ADDRESS; for tcp the port is 1-65535 or * (any free port).
    libzmq itself wraps an out-of-range port silently (99999 binds 34463)."""
    check(isinstance(endpoint, str) and "://" in endpoint and endpoint.split("://", 1)[1] != "",
          f"publish endpoint must look like tcp://HOST:PORT or ipc://PATH (got {endpoint!r})")
    check("\0" not in endpoint, f"publish endpoint {endpoint!r} holds a NUL character, which no endpoint can")
    scheme, _, address = endpoint.partition("://")
    check(scheme != "inproc", f"publish endpoint {endpoint!r} is reachable only from inside the edi-live process; "
                              "use tcp://HOST:PORT or ipc://PATH")
    if scheme == "ipc" and not address.startswith("@"):  # '@': Linux's abstract namespace, no file
        # libzmq unlinks whatever is at the path before it binds: a file there would be deleted
        check(not os.path.lexists(address) or stat.S_ISSOCK(os.lstat(address).st_mode),
              f"publish endpoint {endpoint!r}: {address} exists and is not a socket, and binding would delete it; "
              "choose another path")
    parts = tcp_parts(endpoint)
    if parts is None:
        return
    host, port = parts
    ok = bool(host) and (port == "*" or (port.isdigit() and 1 <= int(port) <= 65535))
    check(ok, f"publish endpoint {endpoint!r}: a tcp endpoint needs HOST:PORT with a port in 1-65535, or * for any "
              f"free port (e.g. tcp://127.0.0.1:5555)")


def tcp_parts(endpoint: str) -> tuple[str, str] | None:
    """'tcp://HOST:PORT' -> (HOST without IPv6 brackets, PORT as written); None for another scheme."""
    scheme, sep, rest = endpoint.partition("://")
    if scheme != "tcp" or not sep:
        return None
    host, _, port = rest.rpartition(":")
    return host.strip("[]"), port


def ipv6_literal(endpoint: str) -> bool:
    """'tcp://[::1]:5555': a tcp endpoint that names an IPv6 address (libzmq binds and connects to one only with
    ZMQ_IPV6 set; a host name is left alone, where IPv6 first would never fall back to an IPv4-only peer)."""
    return endpoint.startswith("tcp://[")


def parse_tcp_endpoint(endpoint: str, flag: str = "--dv-output") -> tuple[str, int]:
    """'tcp://HOST:PORT' -> (host, port); ConfigError otherwise. Port 0 picks a free port."""
    host, port = tcp_parts(endpoint) or ("", "")
    if not host or not port.isdigit() or int(port) > 65535:
        raise ConfigError(f"{flag} must look like tcp://HOST:PORT, e.g. tcp://127.0.0.1:7777 (got {endpoint!r})")
    return host, int(port)


_ANY_HOST = ("*", "0.0.0.0", "::", "")


def check_ports_apart(endpoints: list[tuple[str, str]]) -> None:
    """(flag, endpoint) pairs the node binds: two on one TCP port of one host (or one on every host) cannot both bind,
    which the bind would only report as the port being taken, as if by another program. ConfigError naming both."""
    seen: dict[int, list[tuple[str, str, str]]] = {}
    for flag, endpoint in endpoints:
        host, port = tcp_parts(endpoint) or ("", "")
        if not port.isdigit() or int(port) == 0:
            continue  # not TCP, or a port picked at bind time
        for other_flag, other_endpoint, other_host in seen.get(int(port), []):
            if host == other_host or host in _ANY_HOST or other_host in _ANY_HOST:
                same = "given twice" if other_flag == flag else f"given to {other_flag} and {flag}"
                raise ConfigError(f"port {port} is {same} ({other_endpoint}, {endpoint}): each endpoint the node "
                                  f"binds needs a port of its own")
        seen.setdefault(int(port), []).append((flag, endpoint, host))
