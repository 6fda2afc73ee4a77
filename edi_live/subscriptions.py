"""Whether anyone subscribes to frames: the subscription messages of an XPUB socket, counted per prefix.

A ZeroMQ SUB socket sends `\\x01<prefix>` to the publisher when it subscribes and `\\x00<prefix>` when it
unsubscribes (libzmq sends the latter itself for a subscriber that disconnects or vanishes). A frame message is
delivered to a subscriber whose prefix starts its topic (`b""` matches every topic). The publisher asks
`wanted` before it encodes a frame: with nobody listening it skips the header, the copy and the send.

Only prefixes of the frame topic are kept (at most len(topic) + 1 of them): any other subscription cannot want
frames, and a hostile peer sending millions of distinct prefixes would otherwise grow this table without bound
and make each message cost a pass over it. The others are only counted (`other_messages`).

No I/O here: the publisher reads the socket and hands every message to `apply()`. Reading the socket's EVENTS
costs ~1 µs, so `check_due()` says when to: for every frame while nobody listens (the first frame after a
subscription goes out), at most every `recheck_ns` while someone does (a subscriber that leaves is noticed
that late: the frames in between are sent and dropped by libzmq, as a PUB socket would).
"""

from __future__ import annotations

import collections
import time

DEFAULT_RECHECK_NS = 50_000_000


class Subscriptions:
    """Subscription prefixes seen on one XPUB socket and whether any of them matches `topic`."""

    def __init__(self, topic: bytes, recheck_ns: int = DEFAULT_RECHECK_NS) -> None:
        self.topic = topic
        self.recheck_ns = recheck_ns
        self.wanted = False
        self._prefixes: collections.Counter[bytes] = collections.Counter()  # prefixes of `topic` only
        self._next_check_ns = 0
        self.other_messages = 0  # subscription messages for other topics (e.g. stats), and anything else

    def check_due(self) -> bool:
        """Whether the socket's waiting subscription messages should be read before the next frame."""
        if not self.wanted:
            return True
        now = time.monotonic_ns()
        if now < self._next_check_ns:
            return False
        self._next_check_ns = now + self.recheck_ns
        return True

    def apply(self, message: bytes) -> None:
        """One message received on the XPUB socket (anything but a subscription message is ignored)."""
        if not message or message[0] not in (0, 1) or not self.topic.startswith(message[1:]):
            self.other_messages += 1
            return
        prefix = message[1:]
        if message[0] == 1:
            self._prefixes[prefix] += 1
        elif self._prefixes[prefix] > 1:
            self._prefixes[prefix] -= 1
        else:
            self._prefixes.pop(prefix, None)
        self.wanted = bool(self._prefixes)  # every prefix kept is one of the frame topic's

    def prefixes(self) -> list[bytes]:
        """The prefixes of the frame topic subscribed now (for tests and logs)."""
        return sorted(self._prefixes)
