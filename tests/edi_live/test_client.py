"""edi_live.client against real loopback sockets: subscribe() yields (header, image), newest_only skips to
the newest frame, receives time out, and malformed or oversized messages from a hostile publisher raise
ClientError while the subscriber stays usable."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import textwrap
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq

from edi_live import wire
from edi_live.client import ClientHandshakeError, ClientTimeout, Subscriber, subscribe
from edi_live.datatypes import Reconstruction
from edi_live.errors import ClientError
from edi_live.publisher import Publisher
from tests.edi_live.test_zmq_bind import has_ipv6_loopback

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


def wait_first(sock, sub: Subscriber, parts, also: zmq.Socket | None = None) -> tuple:
    """Send `parts` until the subscriber (and the raw socket `also`, drained) receives something (slow-joiner
    fix); returns what the subscriber got."""
    deadline = time.monotonic() + 10
    got = None
    while time.monotonic() < deadline:
        sock.send_multipart(parts)
        if got is None:
            try:
                item = sub.recv(0.05)
            except ClientError as exc:
                got = ("error", exc)
            else:
                got = ("frame", item) if item is not None else None
        if also is not None and also.poll(50):
            while also.poll(0):
                also.recv_multipart()
            if got is not None:
                return got
        elif also is None and got is not None:
            return got
    raise AssertionError("nothing arrived")


@contextlib.contextmanager
def _feeding(send):
    """send(i) every 20 ms from a thread (i = 1, 2, ...), until the block ends: publishing until a subscriber that
    connects lazily has joined."""
    stop = threading.Event()

    def feed():
        i = 0
        while not stop.wait(0.02):
            i += 1
            send(i)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        yield
    finally:
        stop.set()
        feeder.join(5)


def test_subscribe_yields_header_and_image(pub):
    gen = subscribe(pub.bound_endpoints[0], timeout_s=RECV_S)
    with _feeding(lambda i: pub.submit(make_rec(7))), contextlib.closing(gen):
        header, image = next(gen)
        assert header["n_events"] == 7 and header["v"] == 1
        np.testing.assert_array_equal(image, make_rec(7).image)
        assert not image.flags.writeable  # a view of the received buffer
        header2, _ = next(gen)
        assert header2["seq"] > header["seq"]


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
    probe = sock.context.socket(zmq.SUB)  # sees the same stream: once it has frame 100, `sub` has it queued
    probe.setsockopt(zmq.LINGER, 0)
    probe.setsockopt(zmq.SUBSCRIBE, b"")
    probe.connect(endpoint)
    with Subscriber(endpoint, newest_only=True, rcvhwm=1000) as sub:
        wait_first(sock, sub, good(0), also=probe)
        while sub.recv(0.1) is not None:
            pass
        for i in range(1, 101):
            sock.send_multipart(good(i))
        last = -1
        while last != 100:
            assert probe.poll(int(RECV_S * 1000)), "the backlog never arrived"
            last = msgpack.unpackb(probe.recv_multipart()[1])["seq"]
        probe.close()
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
    ({"layout": "bgr", "channels": 3.0}, "3.0 channels"),  # a TypeError from the reshape before
    ({"layout": ["gray"]}, "layout ['gray']"),  # unhashable: a TypeError from `in`
    ({"dtype": {"u1": 1}}, "dtype {'u1': 1}"),
])
def test_malformed_messages_raise_client_error_and_the_subscriber_recovers(raw_pub, bad, message):
    sock, endpoint = raw_pub
    if bad == "mismatch":
        bad = good(3)
        bad[2] = bad[2][:-10]
    elif isinstance(bad, dict):  # header values of a wrong type, pixels of the size they claim
        header = {**msgpack.unpackb(good(3)[1]), **bad}
        bad = [b"frame", msgpack.packb(header), bytes(64 * 48 * (3 if header["layout"] == "bgr" else 1))]
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
    """Parts each under max_bytes but together over it: received, then refused with a ClientError."""
    sock, endpoint = raw_pub
    big = [bytes(p) for p in wire.encode_frame(make_rec(1, 346, 260), 1, "cam")]
    with Subscriber(endpoint, newest_only=False, max_bytes=89_980) as sub:
        kind, what = wait_first(sock, sub, big)
        assert kind == "error" and isinstance(what, ClientError) and "exceeds the limit of 89980" in str(what)


def test_a_part_over_the_limit_is_never_received_and_the_subscriber_recovers(raw_pub):
    """Issue 15.1: memory is bounded before receiving. A part larger than max_bytes is refused by libzmq from
    its length prefix (the connection is dropped, never the process), the client reconnects by itself, and
    the receive queue is capped so that it holds at most max_queued_bytes."""
    sock, endpoint = raw_pub
    limit = 64 * 1024
    huge = [b"frame", b"\x80", b"\x00" * (3 * limit)]  # 3x the limit, as in the 250 MiB repro
    with Subscriber(endpoint, newest_only=False, max_bytes=limit, max_queued_bytes=16 * limit,
                    rcvhwm=1000) as sub:
        assert sub.rcvhwm == 16
        assert sub._frames.getsockopt(zmq.MAXMSGSIZE) == limit
        assert sub._frames.getsockopt(zmq.RCVHWM) == 16
        kind, _ = wait_first(sock, sub, good(0))  # connected
        assert kind == "frame"
        errors: list[ClientError] = []

        def receive() -> tuple | None:
            try:
                return sub.recv(0.05)
            except ClientError as exc:  # the old client let 3x-limit parts in and rejected them only here
                errors.append(exc)
                return None

        deadline = time.monotonic() + 10
        while sub.reconnects == 0 and not errors:
            assert time.monotonic() < deadline, "the oversized parts neither dropped the connection nor failed"
            for _ in range(40):
                sock.send_multipart(huge)
            receive()
        kind, item = wait_first(sock, sub, good(5))  # the client reconnected by itself
        assert kind == "frame"
        assert not errors, "an oversized part was received into memory"
        assert item[0]["seq"] == 5


_SLOW_READER = textwrap.dedent("""
    import sys, zmq
    from zmq.utils.monitor import parse_monitor_message
    from edi_live.client import Subscriber
    pub = zmq.Context().socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    with Subscriber(f"tcp://127.0.0.1:{port}", newest_only=False, rcvhwm=1, stats=False) as sub:
        while True:  # slow joiner
            pub.send_multipart([b"frame", b"x", b"y"])
            if sub._frames.poll(50):
                break
        monitor = sub._frames.get_monitor_socket(zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_SUCCEEDED)
        for i in range(2000):  # the subscriber's queue fills up: libzmq stops reading the connection
            pub.send_multipart([b"frame", b"x", b"y" * 100_000])
        def event(wanted):  # within 5 s of the previous one; the first connection's events are still queued
            while monitor.poll(5000):
                if parse_monitor_message(monitor.recv_multipart())["event"] == wanted:
                    return True
            return False

        # the old client's ZMTP heartbeat timed out (3 s) and reconnected with the full queue; wait for that
        # disconnect (or for 5 s, when there is none) and the new connection's handshake
        if event(zmq.EVENT_DISCONNECTED):
            print("disconnected, reconnected:", event(zmq.EVENT_HANDSHAKE_SUCCEEDED), flush=True)
        else:
            print("still connected", flush=True)
        n = 0
        while sub._frames.poll(500):  # the old client aborted here: Assertion failed: _input_stopped
            sub._frames.recv_multipart()
            n += 1
        print("drained", n, flush=True)
""")


def test_a_slow_reader_with_a_full_queue_does_not_abort_libzmq():
    """Issue 15.9 (the slow-subscriber abort of test_publisher.py): a ZMTP heartbeat timeout while the receive
    queue is full made libzmq 4.3 reconnect with the full queue and abort on the next read. Run in a child
    process, since the failure is an abort."""
    proc = subprocess.run([sys.executable, "-c", _SLOW_READER], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, f"rc {proc.returncode}: {proc.stdout} {proc.stderr[-500:]}"
    assert "still connected" in proc.stdout and "drained" in proc.stdout


@pytest.mark.skipif(not has_ipv6_loopback(), reason="this machine has no IPv6 loopback")
def test_a_publisher_on_the_ipv6_loopback_is_received():
    # skipped on what the machine lacks, judged by a plain socket: a failure of the publisher's own IPv6 bind is
    # a failure here, not a skip
    p = Publisher(["tcp://[::1]:*"], "cam", sndhwm=1000, stats_interval_s=0.1)
    p.start()
    try:
        gen = subscribe(p.bound_endpoints[0], timeout_s=RECV_S)
        with _feeding(lambda i: p.submit(make_rec(5))), contextlib.closing(gen):
            header, image = next(gen)
        assert p.bound_endpoints[0].startswith("tcp://[::1]:") and header["n_events"] == 5
    finally:
        p.close()


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


@pytest.mark.parametrize("args, kwargs, message", [
    ((None,), {}, "endpoint must be a string"),  # AttributeError from the port check before
    ((5555,), {}, "endpoint must be a string"),
    (("tcp://127.0.0.1:9",), {"rcvhwm": 1.5}, "rcvhwm must be an integer"),  # TypeError from libzmq before
    (("tcp://127.0.0.1:9",), {"rcvhwm": "16"}, "rcvhwm must be an integer"),
    (("tcp://127.0.0.1:9",), {"max_bytes": True}, "positive integers"),  # taken as a 1-byte limit before
])
def test_wrong_argument_types_are_client_errors(args, kwargs, message):
    with pytest.raises(ClientError, match=message):
        Subscriber(*args, **kwargs)


@pytest.mark.parametrize("timeout_s", ["1", [1], True])
def test_a_timeout_that_is_no_number_is_a_client_error(timeout_s):
    with Subscriber("tcp://127.0.0.1:9") as sub, pytest.raises(ClientError, match="timeout_s must be a number"):
        sub.recv(timeout_s)  # a TypeError from the comparison before ("1", [1]); True waited 1 s


def test_sizes_past_libzmqs_integers_are_client_errors_or_capped():
    # setsockopt raised OverflowError (not a ClientError) for a max_bytes over int64 (MAXMSGSIZE), and for a queue
    # of more than 2**31 - 1 messages (RCVHWM is a C int) that max_queued_bytes // max_bytes allowed
    with pytest.raises(ClientError, match="max_bytes"):
        Subscriber("tcp://127.0.0.1:9", max_bytes=2 ** 63)
    with Subscriber("tcp://127.0.0.1:9", rcvhwm=0, max_bytes=1, max_queued_bytes=2 ** 40) as sub:
        assert sub.rcvhwm == sub._frames.getsockopt(zmq.RCVHWM) == 2 ** 31 - 1


def test_numpy_integers_are_sizes_like_ints():
    with Subscriber("tcp://127.0.0.1:9", rcvhwm=np.int64(5), max_bytes=np.int64(1 << 20)) as sub:
        assert (sub.rcvhwm, sub.max_bytes) == (5, 1 << 20)
        assert sub.recv(np.float32(0.0)) is None


def test_subscribe_yields_colour_frames_as_h_w_3_bgr(pub):
    image = np.zeros((48, 64, 3), np.uint8)
    image[..., 0], image[..., 1], image[..., 2] = 10, 20, 30  # B, G, R
    image[5, 7] = (1, 2, 3)
    rec = Reconstruction(image, 70, "latent", 0, -5, 5, 0.2, 0.2, 7)
    gen = subscribe(pub.bound_endpoints[0], timeout_s=RECV_S)
    with _feeding(lambda i: pub.submit(rec)), contextlib.closing(gen):
        header, got = next(gen)
        assert (header["v"], header["layout"], header["channels"]) == (2, "bgr", 3)
        assert got.shape == (48, 64, 3) and np.array_equal(got, image)


def _client_cli(*args: str) -> subprocess.CompletedProcess:
    import os
    from pathlib import Path

    repo = str(Path(__file__).resolve().parents[2])
    return subprocess.run([sys.executable, "-m", "edi_live.client", *args], capture_output=True, text=True,
                          timeout=60, cwd=repo, env={**os.environ, "PYTHONPATH": repo})


def test_the_client_command_prints_one_line_per_frame(pub):
    # `edi-live --help` names `python -m edi_live.client` as what prints the frames; it printed nothing, exit 0
    with _feeding(lambda i: pub.submit(make_rec(i))):
        proc = _client_cli(pub.bound_endpoints[0], "--count", "2", "--timeout-s", "30")
    lines = proc.stdout.splitlines()
    assert proc.returncode == 0 and len(lines) == 2, proc.stderr
    seqs = [int(line.split()[1]) for line in lines]
    assert seqs[1] > seqs[0] and all("latent 64x48" in line and "from cam" in line for line in lines), lines


def test_the_client_command_without_a_publisher_is_one_error_line():
    proc = _client_cli("tcp://127.0.0.1:9", "--timeout-s", "0.2")  # nothing publishes there
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.splitlines() == ["edi-live client: error: no frame from tcp://127.0.0.1:9 within 0.2 s: is "
                                        "edi-live running and publishing there?"]


@pytest.mark.parametrize("endpoint", ["tcp://127.0.0.1:99999", "tcp://127.0.0.1:0", "tcp://127.0.0.1:-5",
                                      "tcp://127.0.0.1:x"])
def test_a_tcp_port_out_of_range_is_a_client_error(endpoint):
    # libzmq wraps a port over 65535 silently: tcp://127.0.0.1:99999 listened on port 34463 for frames, and the
    # user was told only that no frame came ("is edi-live running?")
    with pytest.raises(ClientError, match="port"):
        Subscriber(endpoint)


def test_an_inproc_endpoint_is_a_client_error_not_a_silent_wait():
    # the Subscriber has a ZeroMQ context of its own, and inproc:// reaches only sockets of the same context: it
    # connected, and every receive waited for frames that could never come (the publisher refuses inproc too)
    with pytest.raises(ClientError, match="inproc"):
        Subscriber("inproc://frames")


def test_frames_over_max_bytes_are_named_in_the_timeout_not_a_publisher_that_is_not_running(pub):
    # libzmq drops the connection at a part over max_bytes and the client reconnects, so frames larger than the
    # limit never arrived and subscribe() said only "no frame ...: is edi-live running and publishing there?"
    gen = subscribe(pub.bound_endpoints[0], timeout_s=2.0, max_bytes=1000)  # a 64x48 frame has 3072 pixel bytes
    with _feeding(lambda i: pub.submit(make_rec(i))), contextlib.closing(gen), pytest.raises(ClientTimeout) as info:
        next(gen)
    assert "max_bytes" in str(info.value) and "1000" in str(info.value)


def test_a_timeout_too_large_for_a_float_is_a_wait_not_an_overflow_error(pub):
    # an int timeout past the float range (a "forever" computed as 10 ** 400) raised OverflowError from the
    # deadline's arithmetic, outside ClientError
    with Subscriber(pub.bound_endpoints[0]) as sub, _feeding(lambda i: pub.submit(make_rec(i))):
        assert sub.recv(10 ** 400) is not None
        assert sub.recv_stats(10 ** 400) is not None


def test_a_nan_timeout_is_a_client_error_not_a_wait_for_ever():
    outcome: list = []

    def receive():
        with Subscriber("tcp://127.0.0.1:9") as sub:  # nothing publishes there
            try:
                outcome.append(sub.recv(float("nan")))
            except ClientError as exc:
                outcome.append(exc)

    thread = threading.Thread(target=receive, daemon=True)
    thread.start()
    thread.join(10)
    assert outcome and isinstance(outcome[0], ClientError) and "timeout" in str(outcome[0])


@pytest.mark.parametrize("args,fragment", [
    (["--timeout-s", "nan"], "--timeout-s"), (["--timeout-s", "-1"], "--timeout-s"),
    (["--count", "-3"], "--count"),  # never reached: it printed frames for ever
])
def test_the_client_command_refuses_bad_numbers(args, fragment):
    proc = _client_cli("tcp://127.0.0.1:9", *args)
    assert proc.returncode == 2 and fragment in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


def test_the_client_command_into_a_closed_pipe_ends_quietly(pub):
    # 'python -m edi_live.client | head -2' ended with a BrokenPipeError traceback once head had its lines
    from pathlib import Path

    repo = str(Path(__file__).resolve().parents[2])
    with _feeding(lambda i: pub.submit(make_rec(i))):
        proc = subprocess.Popen([sys.executable, "-m", "edi_live.client", pub.bound_endpoints[0], "--timeout-s", "30"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=repo,
                                env={**os.environ, "PYTHONPATH": repo})
        try:
            assert proc.stdout.readline().startswith("seq ")
            proc.stdout.close()  # the reader goes away, as head does
            err = proc.stderr.read()
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert proc.returncode == 0 and err == "", err


def test_close_twice_is_harmless_and_a_receive_after_close_is_a_client_error():
    # an explicit close() inside 'with Subscriber(...)' raised ZMQError 'Socket operation on non-socket' at the
    # block's end; a receive after close() raised a bare ZMQError
    with Subscriber("tcp://127.0.0.1:9") as sub:
        sub.close()
    sub.close()
    with pytest.raises(ClientError, match="closed"):
        sub.recv(0.1)
    with pytest.raises(ClientError, match="closed"):
        sub.recv_stats(0)


def test_the_client_command_prints_no_control_characters_from_the_publisher(raw_pub):
    # a publisher's 'source' went to the terminal as it came: escape sequences (clear screen, window title) included
    sock, endpoint = raw_pub
    parts = [bytes(p) for p in wire.encode_frame(make_rec(1), 1, "cam\x1b[2J\r\x07evil")]
    with _feeding(lambda i: sock.send_multipart(parts)):
        proc = _client_cli(endpoint, "--count", "1", "--timeout-s", "30")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("\n") == 1 and not any(c in proc.stdout for c in "\x1b\r\x07"), repr(proc.stdout)
    assert "from cam\\x1b[2J\\r\\x07evil" in proc.stdout


def _handshake_error(sub: Subscriber) -> ClientHandshakeError:
    """The error recv() raises once libzmq reported the failed handshakes (it retries every ~0.1 s)."""
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            sub.recv(0.2)
        except ClientHandshakeError as exc:
            return exc
    raise AssertionError("no handshake error within 20 s")


@pytest.mark.skipif(not zmq.has("curve"), reason="libzmq without CURVE")
def test_an_encryption_mismatch_or_a_wrong_key_is_named_instead_of_a_silent_wait(tmp_path):
    # a subscriber with the wrong --curve-server-key, or one when the publisher does not encrypt (or none when it
    # does), waited for ever: 'no frame ... is edi-live running and publishing there?' with --timeout-s
    from edi_live.publisher import generate_curve_keys

    public, secret = generate_curve_keys(tmp_path / "keys")
    other_public, _ = generate_curve_keys(tmp_path / "other")
    plain = Publisher(["tcp://127.0.0.1:*"], "cam")
    encrypted = Publisher(["tcp://127.0.0.1:*"], "cam", curve_secret_key=secret)
    plain.start()
    encrypted.start()
    try:
        cases = [(plain, public, "does not encrypt"), (encrypted, None, "encrypts (CURVE"),
                 (encrypted, other_public, "--curve-server-key is not the public key")]
        for pub, key, fragment in cases:
            endpoint = pub.bound_endpoints[0]
            with Subscriber(endpoint, curve_server_key=key) as sub:
                error = _handshake_error(sub)
            assert fragment in str(error) and endpoint in str(error) and "\n" not in str(error), str(error)
    finally:
        plain.close()
        encrypted.close()


def test_a_server_that_is_not_zeromq_is_named():
    # e.g. the node's --dv-output port given to the client: a silent wait for ever
    import socket

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(4)
        endpoint = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        stop = threading.Event()

        def serve():  # what a DV server does: send its header at once, never read
            server.settimeout(0.1)
            held = []
            while not stop.is_set():
                try:
                    conn, _ = server.accept()
                except OSError:
                    continue
                conn.sendall(b"\x20\x0c\x00\x00" + b"IOHE" + b"\x00" * 64)
                held.append(conn)
            for conn in held:
                conn.close()

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        try:
            with Subscriber(endpoint) as sub:
                error = _handshake_error(sub)
        finally:
            stop.set()
            thread.join(5)
    assert "ZeroMQ" in str(error) and endpoint in str(error), str(error)


def test_frames_drained_before_a_message_of_too_many_parts_count_as_skipped(monkeypatch):
    # newest_only drains to the newest message; one of 5 parts met there raised at once, and the frames already
    # drained were neither handed over nor counted in `skipped`, so a viewer counted them as lost on the wire.
    # The socket's messages are scripted (a real publisher cannot say when all of them are queued here).
    queued = [good(1), good(2), good(3), ClientError("a message of 5 parts arrived")]

    def recv_message(sock, flags):
        if not queued:
            raise zmq.Again()
        item = queued.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    with Subscriber("tcp://127.0.0.1:9", newest_only=True) as sub:
        monkeypatch.setattr(sub, "_recv_message", recv_message)
        with pytest.raises(ClientError, match="a message of 5 parts"):
            sub.recv(0)
        assert sub.skipped == 3 and sub.received == 0  # frames 1, 2 and 3: drained, never shown
        queued[:] = [good(4), good(5)]
        header, _ = sub.recv(0)
        assert header["seq"] == 5 and sub.skipped == 4 and sub.received == 1


def test_a_message_of_a_million_parts_is_refused_without_holding_them(raw_pub):
    # libzmq bounds a part's size, not the number of parts: 2 million empty parts (4 MB on the wire) became
    # 2 million Python objects (RSS +1.1 GB) before the part count was checked
    import tracemalloc

    sock, endpoint = raw_pub
    with Subscriber(endpoint, newest_only=False) as sub:
        kind, _ = wait_first(sock, sub, good(1))  # the subscription is in place (and frame 1 received)
        assert kind == "frame"
        while sub.recv(0.2) is not None:
            pass
        sock.send_multipart([b"frame"] + [b""] * 1_000_000)
        sock.send_multipart(good(2))
        assert sub._frames.poll(20_000)
        tracemalloc.start()
        try:
            with pytest.raises(ClientError, match="1000001"):
                sub.recv(20)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 10_000_000, peak
        header, _ = sub.recv(RECV_S)  # the next message is read as usual
        assert header["seq"] == 2
