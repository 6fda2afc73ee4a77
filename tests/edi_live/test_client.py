"""edi_live.client against real loopback sockets: subscribe() yields (header, image), newest_only skips to
the newest frame, receives time out, and malformed or oversized messages from a hostile publisher raise
ClientError while the subscriber stays usable."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
import zmq

from edi_live import wire
from edi_live.client import ClientTimeout, Subscriber, subscribe
from edi_live.datatypes import Reconstruction
from edi_live.errors import ClientError
from edi_live.publisher import Publisher

RECV_S = 5.0


def make_rec(i: int, w: int = 64, h: int = 48) -> Reconstruction:
    image = np.full((h, w), i % 256, dtype=np.uint8)
    image[0, :] = np.arange(w) % 256
    return Reconstruction(image, 10 * i, "latent", 0, -5, 5, 0.2, 0.2, i)


@pytest.fixture
def raw_pub():
    """A bare PUB socket the test controls byte by byte (a hostile or buggy publisher)."""
    ctx = zmq.Context()
    sock = ctx.socket(zmq.PUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.bind("tcp://127.0.0.1:*")
    yield sock, sock.getsockopt_string(zmq.LAST_ENDPOINT)
    ctx.destroy(linger=0)


@pytest.fixture
def pub():
    p = Publisher(["tcp://127.0.0.1:*"], "cam", sndhwm=1000, stats_interval_s=0.1)
    p.start()
    yield p
    p.close()


def good(i: int = 1) -> list:
    return [bytes(p) for p in wire.encode_frame(make_rec(i), i, "cam")]


def wait_first(sock, sub: Subscriber, parts) -> tuple:
    """Send `parts` until the subscriber receives something (slow-joiner fix); returns what it got."""
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        sock.send_multipart(parts)
        try:
            item = sub.recv(0.05)
        except ClientError as exc:
            return ("error", exc)
        if item is not None:
            return ("frame", item)
    raise AssertionError("nothing arrived")


def test_subscribe_yields_header_and_image(pub):
    stop = threading.Event()

    def feed():  # publish until the subscriber (connected lazily by next()) has joined
        while not stop.wait(0.02):
            pub.submit(make_rec(7))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    gen = subscribe(pub.bound_endpoints[0], timeout_s=RECV_S)
    try:
        header, image = next(gen)
        assert header["n_events"] == 7 and header["v"] == 1
        np.testing.assert_array_equal(image, make_rec(7).image)
        assert not image.flags.writeable  # a view of the received buffer
        header2, _ = next(gen)
        assert header2["seq"] > header["seq"]
    finally:
        stop.set()
        feeder.join(5)
        gen.close()


def test_subscribe_times_out_with_a_clear_error():
    gen = subscribe("tcp://127.0.0.1:9", timeout_s=0.2)  # nothing publishes there
    with pytest.raises(ClientTimeout, match="no frame from tcp://127.0.0.1:9 within 0.2 s"):
        next(gen)
    assert issubclass(ClientTimeout, TimeoutError) and issubclass(ClientTimeout, ClientError)


def test_recv_returns_none_on_timeout():
    with Subscriber("tcp://127.0.0.1:9") as sub:
        t0 = time.monotonic()
        assert sub.recv(0.15) is None
        assert sub.recv_stats(0.05) is None
        assert time.monotonic() - t0 < 5  # a generous bound: it must not hang


def test_newest_only_skips_to_the_newest_frame(raw_pub):
    sock, endpoint = raw_pub
    with Subscriber(endpoint, newest_only=True, rcvhwm=1000) as sub:
        wait_first(sock, sub, good(0))
        while sub.recv(0.1) is not None:
            pass
        for i in range(1, 101):
            sock.send_multipart(good(i))
        time.sleep(0.3)  # let the backlog reach the subscriber's queue
        seqs = []
        while (item := sub.recv(0.5)) is not None:
            seqs.append(item[0]["seq"])
    assert seqs[-1] == 100
    assert len(seqs) < 50, f"newest_only should skip the backlog, got {len(seqs)} frames"
    assert seqs == sorted(seqs)
    assert sub.skipped >= 50


def test_lossless_mode_keeps_every_frame(raw_pub):
    sock, endpoint = raw_pub
    with Subscriber(endpoint, newest_only=False) as sub:
        wait_first(sock, sub, good(0))
        while sub.recv(0.1) is not None:
            pass
        for i in range(1, 51):
            sock.send_multipart(good(i))
        seqs = [sub.recv(RECV_S)[0]["seq"] for _ in range(50)]
    assert seqs == list(range(1, 51))


@pytest.mark.parametrize("bad, message", [
    ([b"frame", b"\xc1", b"xx"], "not valid msgpack"),
    ([b"frame", msgpack.packb({"v": 1}), b"xx"], "'seq'"),
    ([b"frame", b"only two"], "3 parts"),
    ("mismatch", "pixel part has"),
])
def test_malformed_messages_raise_client_error_and_the_subscriber_recovers(raw_pub, bad, message):
    sock, endpoint = raw_pub
    if bad == "mismatch":
        bad = good(3)
        bad[2] = bad[2][:-10]
    with Subscriber(endpoint, newest_only=False) as sub:
        kind, what = wait_first(sock, sub, bad)
        assert kind == "error" and message in str(what)
        while True:  # drain the other copies of the bad message
            try:
                if sub.recv(0.2) is None:
                    break
            except ClientError:
                pass
        kind, (header, _) = wait_first(sock, sub, good(9))
        assert kind == "frame" and header["seq"] == 9


def test_oversized_messages_are_rejected(raw_pub):
    sock, endpoint = raw_pub
    big = [bytes(p) for p in wire.encode_frame(make_rec(1, 346, 260), 1, "cam")]
    with Subscriber(endpoint, newest_only=False, max_bytes=50_000) as sub:
        kind, what = wait_first(sock, sub, big)
        assert kind == "error" and isinstance(what, ClientError) and "exceeds the limit of 50000" in str(what)


def test_stats_arrive_on_their_own_socket(pub):
    with Subscriber(pub.bound_endpoints[0], newest_only=False) as sub:
        stats = sub.recv_stats(RECV_S)
        assert stats is not None and stats["v"] == 1 and "frames_sent" in stats
        assert sub.last_stats is stats
        pub.submit(make_rec(4))  # a frame sent while we waited for stats is still there for recv()
        deadline = time.monotonic() + 10
        item = None
        while item is None and time.monotonic() < deadline:
            item = sub.recv(0.2)
            if item is None:
                pub.submit(make_rec(4))
        assert item is not None and item[0]["n_events"] == 4


def test_bad_endpoint_and_key_are_client_errors(tmp_path):
    with pytest.raises(ClientError, match="cannot connect"):
        Subscriber("nonsense://x")
    with pytest.raises(ClientError, match="CURVE server public key"):
        Subscriber("tcp://127.0.0.1:9", curve_server_key=tmp_path / "missing.key")
