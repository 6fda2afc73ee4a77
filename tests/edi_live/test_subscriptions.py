"""Subscriptions: whether anyone wants frames, from the subscription messages of a real XPUB socket on loopback."""

from __future__ import annotations

import time

import pytest
import zmq

from edi_live.subscriptions import Subscriptions

WAIT_MS = 5000


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


def settle(subs: Subscriptions, sock: zmq.Socket, expected: list[bytes]) -> None:
    """Wait (poll with a timeout, no sleeps) until the subscription messages in flight have been applied."""
    deadline = time.monotonic() + WAIT_MS / 1000
    while subs.prefixes() != expected:
        assert time.monotonic() < deadline, f"subscriptions stayed {subs.prefixes()}, expected {expected}"
        sock.poll(50, zmq.POLLIN)
        subs.drain(sock)


def test_nobody_then_a_frame_subscriber_then_nobody_again(xpub):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=0)
    assert not subs.wanted(sock)
    stats_only = subscriber(b"stats")
    settle(subs, sock, [b"stats"])
    assert not subs.wanted(sock)  # a stats subscriber does not want frames
    frames = subscriber(b"frame")
    settle(subs, sock, [b"frame", b"stats"])
    assert subs.wanted(sock)
    frames.setsockopt(zmq.UNSUBSCRIBE, b"frame")
    settle(subs, sock, [b"stats"])
    assert not subs.wanted(sock)
    stats_only.close(0)  # a subscriber that goes away unsubscribes (libzmq sends it for the peer)
    settle(subs, sock, [])


@pytest.mark.parametrize("prefix", [b"", b"fr", b"frame"])
def test_any_prefix_of_the_topic_wants_it(xpub, prefix):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=0)
    subscriber(prefix)
    settle(subs, sock, [prefix])
    assert subs.wanted(sock)


def test_two_subscribers_leave_one_at_a_time(xpub):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=0)
    first = subscriber(b"frame")
    settle(subs, sock, [b"frame"])
    second = subscriber(b"")
    settle(subs, sock, [b"", b"frame"])
    first.close(0)
    settle(subs, sock, [b""])
    assert subs.wanted(sock)  # the one left still takes every topic
    second.close(0)
    settle(subs, sock, [])
    assert not subs.wanted(sock)


def test_while_wanted_the_socket_is_read_only_every_recheck_interval(xpub):
    sock, subscriber = xpub
    subs = Subscriptions(b"frame", recheck_ns=10**12)
    sub = subscriber(b"frame")
    settle(subs, sock, [b"frame"])
    assert subs.wanted(sock)  # starts the interval
    sub.close(0)
    assert sock.poll(WAIT_MS, zmq.POLLIN)  # the unsubscription is waiting on the socket...
    assert subs.wanted(sock)  # ... and not read before the interval ends
