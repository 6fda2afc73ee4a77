"""Subscriptions: whether anyone wants frames, from the subscription messages of a real XPUB socket on loopback."""

from __future__ import annotations

import time

import pytest
import zmq

from edi_live.subscriptions import Subscriptions

WAIT_S = 5.0


@pytest.fixture
def xpub():
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, 0)
    port = sock.bind_to_random_port("tcp://127.0.0.1")
    subs = []

    def subscriber(*prefixes: bytes) -> zmq.Socket:
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.connect(f"tcp://127.0.0.1:{port}")
        for prefix in prefixes:
            sub.setsockopt(zmq.SUBSCRIBE, prefix)
        subs.append(sub)
        return sub

    yield sock, subscriber
    for sub in subs:
        sub.close(0)
    sock.close(0)
    ctx.term()


def settle(subs: Subscriptions, sock: zmq.Socket, expected: list[bytes], others: int | None = None) -> None:
    """Hand the XPUB socket's messages to `subs` (poll with a timeout, no sleeps) until it holds `expected` (and
    has counted `others` messages for other topics)."""
    deadline = time.monotonic() + WAIT_S
    while subs.prefixes() != expected or (others is not None and subs.other_messages != others):
        assert time.monotonic() < deadline, f"subscriptions stayed {subs.prefixes()}, expected {expected}"
        if sock.poll(50, zmq.POLLIN):
            subs.apply(sock.recv())


def test_nobody_then_a_frame_subscriber_then_nobody_again(xpub):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=0)
    assert not subs.wanted
    stats_only = subscriber(b"stats")
    settle(subs, sock, [], others=1)
    assert not subs.wanted  # a stats subscriber does not want frames
    frames = subscriber(b"frame")
    settle(subs, sock, [b"frame"])
    assert subs.wanted
    frames.setsockopt(zmq.UNSUBSCRIBE, b"frame")
    settle(subs, sock, [])
    assert not subs.wanted
    stats_only.close(0)  # a subscriber that goes away unsubscribes (libzmq sends it for the peer)
    settle(subs, sock, [], others=2)


def test_subscriptions_that_cannot_want_frames_are_counted_not_kept():
    # a hostile peer sending a million distinct prefixes grew the table without bound, and every message then cost
    # a pass over it
    subs = Subscriptions(b"frame")
    for i in range(100_000):
        subs.apply(b"\x01" + i.to_bytes(4, "little"))
    assert subs.prefixes() == [] and subs.other_messages == 100_000 and not subs.wanted
    subs.apply(b"\x01fra")
    assert subs.wanted and subs.prefixes() == [b"fra"]


@pytest.mark.parametrize("prefix", [b"", b"fr", b"frame"])
def test_any_prefix_of_the_topic_wants_it(xpub, prefix):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=0)
    subscriber(prefix)
    settle(subs, sock, [prefix])
    assert subs.wanted


def test_two_subscribers_leave_one_at_a_time(xpub):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=0)
    first = subscriber(b"frame")
    settle(subs, sock, [b"frame"])
    second = subscriber(b"")
    settle(subs, sock, [b"", b"frame"])
    first.close(0)
    settle(subs, sock, [b""])
    assert subs.wanted  # the one left still takes every topic
    second.close(0)
    settle(subs, sock, [])
    assert not subs.wanted


def test_repeated_subscriptions_are_counted_and_other_messages_ignored():
    subs = Subscriptions(b"frame")
    for message in (b"\x01frame", b"\x01frame", b"\x02frame", b"", b"\x00frame"):
        subs.apply(message)
    assert subs.wanted and subs.prefixes() == [b"frame"] and subs.other_messages == 2
    subs.apply(b"\x00frame")
    assert not subs.wanted and subs.prefixes() == []


def test_the_socket_is_read_for_every_frame_while_nobody_listens_and_seldom_otherwise():
    subs = Subscriptions(b"frame", recheck_ns=10**12)
    assert subs.check_due() and subs.check_due()  # nobody: a subscription must be seen at the next frame
    subs.apply(b"\x01frame")
    assert subs.check_due()  # the first check starts the interval ...
    assert not subs.check_due()  # ... and the next one waits for it to end
