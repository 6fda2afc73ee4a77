"""Whether anyone subscribes to frames: the subscription messages an XPUB socket receives, counted per prefix.

A ZeroMQ SUB socket sends `\\x01<prefix>` to the publisher when it subscribes and `\\x00<prefix>` when it
unsubscribes or disconnects (libzmq sends the latter for a vanished subscriber itself). A frame message is
delivered to a subscriber whose prefix starts its topic (`b""` matches every topic). The publisher asks
`wanted()` before it encodes a frame: with nobody listening it skips the header, the copy and the send.

Owns no socket: the caller passes the XPUB socket and holds whatever lock serialises it. Reading the socket's
EVENTS costs ~1 µs, so while frames are wanted the socket is read at most every `recheck_ns` (a subscriber
that leaves is noticed that late: the frames in between are sent and dropped by libzmq, as before); while
nobody listens it is read for every frame, so the first frame after a subscription goes out.
"""

from __future__ import annotations

import collections
import time

import zmq

_POLLIN = int(zmq.POLLIN)
_EVENTS = int(zmq.EVENTS)
_NOBLOCK = int(zmq.NOBLOCK)
DEFAULT_RECHECK_NS = 50_000_000


class Subscriptions:
    """Subscription prefixes seen on one XPUB socket and whether any of them matches `topic`."""

    def __init__(self, topic: bytes, recheck_ns: int = DEFAULT_RECHECK_NS) -> None:
        self.topic = topic
        self.recheck_ns = recheck_ns
        self._prefixes: collections.Counter[bytes] = collections.Counter()
        self._wanted = False
        self._next_check_ns = 0

    def wanted(self, sock: zmq.Socket) -> bool:
        """Whether a subscriber wants `topic` (reads the socket's pending subscription messages when due)."""
        if self._wanted:
            now = time.monotonic_ns()
            if now < self._next_check_ns:
                return True
            self._next_check_ns = now + self.recheck_ns
        self.drain(sock)
        return self._wanted

    def drain(self, sock: zmq.Socket) -> None:
        """Apply every subscription message waiting on the socket."""
        changed = False
        while sock.getsockopt(_EVENTS) & _POLLIN:
            try:
                message = sock.recv(_NOBLOCK)
            except zmq.Again:
                break
            if not message or message[0] not in (0, 1):
                continue  # not a subscription message (XPUB passes other messages from subscribers through)
            prefix = message[1:]
            if message[0] == 1:
                self._prefixes[prefix] += 1
            elif self._prefixes[prefix] > 1:
                self._prefixes[prefix] -= 1
            else:
                self._prefixes.pop(prefix, None)
            changed = True
        if changed:
            self._wanted = any(self.topic.startswith(prefix) for prefix in self._prefixes)

    def prefixes(self) -> list[bytes]:
        """The prefixes subscribed now (for tests and logs)."""
        return sorted(self._prefixes)
