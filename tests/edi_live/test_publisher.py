"""The Publisher over real loopback sockets (tcp://127.0.0.1:*, resolved): round trip, seq, stats, slow and
dead subscribers, fan-out, bind errors and CURVE. Every receive has a timeout; sockets close with linger 0."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
import zmq

from edi_live.client import ClientHandshakeError, Subscriber
from edi_live.datatypes import Reconstruction
from edi_live.errors import BindError, PublishError
from edi_live.publisher import Publisher, generate_curve_keys, main

ANY = "tcp://127.0.0.1:*"
RECV_S = 5.0


def make_rec(i: int, w: int = 240, h: int = 180, arrival_ns: int = 0) -> Reconstruction:
    image = ((np.arange(w * h, dtype=np.int64).reshape(h, w) + 7 * i) % 251).astype(np.uint8)
    return Reconstruction(image=image, t_us=1_000_000 + 1000 * i, kind="deblurred" if i % 10 == 0 else "latent",
                          ref_t_us=1_000_000, exposure_start_us=995_000, exposure_end_us=1_005_000,
                          c_on=0.2, c_off=0.2, n_events=i, arrival_ns=arrival_ns)


def sync(pub: Publisher, *subs: Subscriber) -> int:
    """Submit probe frames until every subscriber has received one (slow-joiner fix), then drain each one up to
    the last probe; returns the next seq."""
    seen = [-1] * len(subs)
    submitted = pub.stats()["sent"] + pub.stats()["unsubscribed"]
    deadline = time.monotonic() + 10
    while min(seen) < 0:
        assert time.monotonic() < deadline, "subscribers never received a probe frame"
        pub.submit(make_rec(0, 4, 2))
        submitted += 1
        for k, sub in enumerate(subs):
            while (item := sub.recv(0.02)) is not None:
                seen[k] = item[0]["seq"]
    # probes submitted before any subscription reached the publisher are not sent (counted as unsubscribed)
    wait_until(lambda: pub.stats()["sent"] + pub.stats()["unsubscribed"] == submitted,
               "the publisher never handled every probe")
    last = pub.stats()["last_seq"]
    for sub, seq in zip(subs, seen):  # drain stragglers: every probe up to the last one
        while seq < last:
            item = sub.recv(RECV_S)
            assert item is not None, f"probe {last} never arrived"
            seq = item[0]["seq"]
    return last + 1


def wait_until(condition, message: str, timeout_s: float = 10.0) -> None:
    """Poll `condition` (a cheap check) until it holds; fail with `message` after `timeout_s`."""
    done = threading.Event()
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, message
        done.wait(0.005)


@pytest.fixture
def publisher():
    made = []

    def factory(*args, **kwargs) -> Publisher:
        args = args or ([ANY], "DAVIS346_test")
        pub = Publisher(*args, **kwargs)
        pub.start()
        made.append(pub)
        return pub

    yield factory
    for pub in made:
        pub.close()


def test_round_trip_headers_pixels_and_seq(publisher):
    pub = publisher(sndhwm=1000)
    assert pub.bound_endpoints[0].startswith("tcp://127.0.0.1:") and not pub.bound_endpoints[0].endswith("*")
    with Subscriber(pub.bound_endpoints[0], newest_only=False) as sub:
        seq0 = sync(pub, sub)
        recs = [make_rec(i) for i in range(1, 41)]
        for rec in recs:
            pub.submit(rec)
        for k, rec in enumerate(recs):
            item = sub.recv(RECV_S)
            assert item is not None, f"frame {k} never arrived"
            header, image = item
            assert header["seq"] == seq0 + k  # +1 per frame message
            assert header["source"] == "DAVIS346_test"
            assert (header["t"], header["kind"], header["n_events"]) == (rec.t_us, rec.kind, rec.n_events)
            assert (header["ref_t"], header["exp_start"], header["exp_end"]) == (1_000_000, 995_000, 1_005_000)
            assert header["c"] == pytest.approx(0.2)
            np.testing.assert_array_equal(image, rec.image)



def test_inline_and_queued_sends_keep_submit_order(publisher):
    """submit() sends on the caller's thread when the socket is free and queues while the publisher thread uses
    it; frames queued meanwhile must leave before any later frame, whichever thread sends it."""
    pub = publisher([ANY], "cam", sndhwm=10_000, inbox_size=1000)
    senders: list[str] = []
    send_frame = pub._send_frame

    def spy(sock, rec):
        senders.append(threading.current_thread().name)
        send_frame(sock, rec)

    pub._send_frame = spy
    with Subscriber(pub.bound_endpoints[0], newest_only=False, rcvhwm=0, stats=False) as sub:
        sync(pub, sub)
        senders.clear()
        n = 40
        for i in range(n):
            pub.submit(make_rec(i, 16, 8))  # inline: the socket is free
        with pub._sock_lock:  # as while the publisher thread sends a batch or the stats
            for i in range(n, 2 * n):
                pub.submit(make_rec(i, 16, 8))  # must queue
            assert pub.pending() == n
        for i in range(2 * n, 3 * n):
            pub.submit(make_rec(i, 16, 8))  # the queue is not empty yet: these must not overtake it
        got = []
        while len(got) < 3 * n:
            item = sub.recv(RECV_S)
            assert item is not None, f"only {len(got)} of {3 * n} frames arrived"
            got.append(item[0])
    assert [h["n_events"] for h in got] == list(range(3 * n))
    assert [h["seq"] for h in got] == list(range(got[0]["seq"], got[0]["seq"] + 3 * n))
    me = threading.current_thread().name
    assert senders[:n] == [me] * n and "publisher" in senders[n:]  # both paths were taken



def test_a_socket_failure_in_an_inline_send_is_reported_as_the_publishers(publisher):
    """submit() runs sends on the caller's thread; a socket error there must not escape into the caller (the
    EDI worker) but reach on_error, as it would from the publisher thread."""
    failures: list[BaseException] = []
    failed = threading.Event()
    pub = publisher([ANY], "cam", on_error=lambda exc: (failures.append(exc), failed.set()))

    def broken(sock, rec):
        raise zmq.ZMQError(zmq.ETERM)

    pub._send_frame = broken
    pub.submit(make_rec(1))  # must not raise
    # (had the thread held the socket, the frame was queued: it fails there)
    assert failed.wait(5), "the failure never reached on_error"
    assert len(failures) == 1 and isinstance(failures[0], zmq.ZMQError)
    assert pub.error is failures[0]


def test_stats_message_merges_provider_and_measures_latency(publisher):
    calls = []

    def provider():
        calls.append(1)
        return {"events_per_s": 1.25e6, "c": 0.21, "reestimations": 2, "ring_occupancy": 0.5,
                "frames_per_s": 99.0}

    pub = publisher([ANY], "cam", stats_provider=provider, stats_interval_s=0.1, sndhwm=1000)
    with Subscriber(pub.bound_endpoints[0], newest_only=False) as sub:
        sync(pub, sub)
        five_ms_ago = time.monotonic_ns() - 5_000_000
        for i in range(20):
            pub.submit(make_rec(i, arrival_ns=five_ms_ago))
        deadline = time.monotonic() + RECV_S
        stats = None
        while time.monotonic() < deadline:
            stats = sub.recv_stats(0.5)
            if stats and stats["frames_sent"] >= 20 and stats["latency_p50_us"] is not None:
                break
        assert stats is not None, "no stats message within the timeout"
    assert calls
    assert stats["v"] == 1 and stats["source"] == "cam"
    assert stats["events_per_s"] == 1.25e6 and stats["reestimations"] == 2 and stats["ring_occupancy"] == 0.5
    assert stats["frames_per_s"] == 99.0  # the node's own rate wins over the publisher's
    assert stats["publish_dropped"] == 0
    # latency = send time - arrival of the last included event; the events arrived >= 5 ms before sending
    assert stats["latency_p50_us"] >= 5000 and stats["latency_p99_us"] >= stats["latency_p50_us"]


def test_a_failing_stats_provider_does_not_stop_frames(publisher):
    def provider():
        raise RuntimeError("boom")

    pub = publisher([ANY], "cam", stats_provider=provider, stats_interval_s=0.05)
    with Subscriber(pub.bound_endpoints[0]) as sub:
        sync(pub, sub)
        stats = sub.recv_stats(RECV_S)
        assert stats is not None and "frames_sent" in stats
        pub.submit(make_rec(3))
        assert sub.recv(RECV_S) is not None


def test_slow_subscriber_never_blocks_and_fast_one_keeps_up(publisher):
    """A subscriber that never reads gets dropped by PUB once its queues fill; the fast one gets every frame."""
    pub = publisher([ANY], "cam", sndhwm=16)
    n = 2000  # 2000 x 307 kB = 614 MB: far beyond what the slow peer's kernel buffers and HWM can hold
    with Subscriber(pub.bound_endpoints[0], newest_only=False, rcvhwm=1, stats=False) as slow, \
            Subscriber(pub.bound_endpoints[0], newest_only=False, stats=False) as fast:
        seq0 = sync(pub, slow, fast)
        for i in range(n):
            pub.submit(make_rec(i, 640, 480))
            item = fast.recv(RECV_S)
            assert item is not None, f"fast subscriber starved at frame {i}: the slow one blocked the publisher"
            assert item[0]["seq"] == seq0 + i
            assert pub.pending() <= 64
        slow_seqs = []
        while (item := slow.recv(0.5)) is not None:
            slow_seqs.append(item[0]["seq"])
    assert len(slow_seqs) < n, "the slow subscriber should have lost frames (PUB drops for it)"
    assert slow_seqs == sorted(slow_seqs)
    assert pub.stats()["dropped"] == 0  # drops for one slow peer are not publisher drops


def test_burst_submit_never_waits_and_counts_inbox_drops(publisher):
    pub = publisher([ANY], "cam", inbox_size=8)
    n = 5000
    with Subscriber(pub.bound_endpoints[0], newest_only=False, rcvhwm=1, stats=False):  # never reads
        done = threading.Event()
        max_pending = []

        def burst():
            for i in range(n):
                pub.submit(make_rec(i % 50))
                max_pending.append(pub.pending())
            done.set()

        thread = threading.Thread(target=burst, daemon=True)
        thread.start()
        assert done.wait(30), "submit() blocked"
        pub.close()
    assert max(max_pending) <= 8  # memory stays bounded
    stats = pub.stats()
    # frames submitted before the subscription reached the publisher are counted as unsubscribed (and take no seq)
    assert stats["sent"] + stats["dropped_inbox"] + stats["dropped_socket"] + stats["unsubscribed"] == n
    assert stats["last_seq"] == stats["sent"] + stats["dropped_socket"] - 1


def test_two_subscribers_both_receive(publisher):
    pub = publisher(sndhwm=1000)
    with Subscriber(pub.bound_endpoints[0], newest_only=False) as a, \
            Subscriber(pub.bound_endpoints[0], newest_only=False) as b:
        seq0 = sync(pub, a, b)
        for i in range(10):
            pub.submit(make_rec(i))
        for sub in (a, b):
            seqs = [sub.recv(RECV_S)[0]["seq"] for _ in range(10)]
            assert seqs == list(range(seq0, seq0 + 10))


def test_several_endpoints_are_bound(publisher, tmp_path):
    pub = publisher([ANY, f"ipc://{tmp_path}/frames.sock"], "cam", sndhwm=1000)
    assert len(pub.bound_endpoints) == 2 and pub.bound_endpoints[1].startswith("ipc://")
    with Subscriber(pub.bound_endpoints[1], newest_only=False) as sub:
        sync(pub, sub)
        pub.submit(make_rec(5))
        header, _ = sub.recv(RECV_S)
        assert header["n_events"] == 5


def test_bind_to_a_port_in_use_raises_bind_error():
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    port = holder.getsockname()[1]
    try:
        pub = Publisher([f"tcp://127.0.0.1:{port}"], "cam")
        with pytest.raises(BindError, match="already in use") as info:
            pub.start()
        assert "\n" not in str(info.value) and str(port) in str(info.value)
        pub.close()
        assert not pub._thread.is_alive()
    finally:
        holder.close()


@pytest.mark.parametrize("endpoint", ["tcp://127.0.0.1", "nonsense", "tcp://256.1.1.1:5555"])
def test_bad_endpoints_raise_bind_error(endpoint):
    pub = Publisher([endpoint], "cam")
    with pytest.raises(BindError, match="cannot publish on"):
        pub.start()
    pub.close()


def test_curve_encrypted_subscriber_receives_and_plain_one_does_not(publisher, tmp_path):
    public, secret = generate_curve_keys(tmp_path / "keys")
    pub = publisher([ANY], "cam", curve_secret_key=secret, sndhwm=1000)
    endpoint = pub.bound_endpoints[0]
    with Subscriber(endpoint, newest_only=False, curve_server_key=public) as enc, \
            Subscriber(endpoint, newest_only=False) as plain:
        sync(pub, enc)
        for i in range(20):
            pub.submit(make_rec(i))
        got = [enc.recv(RECV_S) for _ in range(20)]
        assert all(item is not None for item in got)
        np.testing.assert_array_equal(got[-1][1], make_rec(19).image)
        with pytest.raises(ClientHandshakeError, match="encrypts"):  # nothing decrypts for a plain subscriber
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                assert plain.recv(0.2) is None


def test_curve_key_problems_are_clear(tmp_path):
    public, _ = generate_curve_keys(tmp_path)
    for key, message in [(tmp_path / "missing.key_secret", "cannot read"), (public, "no secret key")]:
        pub = Publisher([ANY], "cam", curve_secret_key=key)
        with pytest.raises(PublishError, match=message):
            pub.start()
        pub.close()


def test_gen_curve_keys_command(tmp_path, capsys):
    assert main(["--gen-curve-keys", str(tmp_path / "k")]) == 0
    assert (tmp_path / "k" / "server.key").is_file() and (tmp_path / "k" / "server.key_secret").is_file()
    assert "server.key_secret" in capsys.readouterr().out
    assert (tmp_path / "k" / "server.key_secret").stat().st_mode & 0o077 == 0


def test_close_is_prompt_and_idempotent_with_a_stalled_peer():
    pub = Publisher([ANY], "cam")
    pub.start()
    ctx = zmq.Context()
    stalled = ctx.socket(zmq.SUB)
    stalled.setsockopt(zmq.LINGER, 0)
    stalled.setsockopt(zmq.RCVHWM, 1)
    stalled.setsockopt(zmq.SUBSCRIBE, b"")
    stalled.connect(pub.bound_endpoints[0])
    try:
        for i in range(500):
            pub.submit(make_rec(i))
        pub.close(timeout_s=5)  # raises PublishError if the thread hangs on linger
        pub.close()
        assert not pub._thread.is_alive()
    finally:
        ctx.destroy(linger=0)


def test_invalid_limits_are_refused():
    with pytest.raises(PublishError):
        Publisher([], "cam")
    with pytest.raises(PublishError):
        Publisher([ANY], "cam", inbox_size=0)


def test_frames_nobody_subscribes_to_are_counted_not_sent(publisher):
    """XPUB: with no frame subscriber the publisher neither encodes nor sends (a stats-only subscriber does not
    count); the first frames after a subscription go out again with consecutive seq."""
    pub = publisher([ANY], "cam", sndhwm=1000)
    for i in range(5):
        pub.submit(make_rec(i, 8, 4))
    wait_until(lambda: pub.stats()["unsubscribed"] == 5, "frames without a subscriber were not counted")
    assert pub.stats()["sent"] == 0 and pub.stats()["last_seq"] == -1
    with Subscriber(pub.bound_endpoints[0], newest_only=False) as sub:
        assert sub.recv_stats(timeout_s=RECV_S) is not None  # stats still flow to a stats subscriber
        seq0 = sync(pub, sub)
        for i in range(1, 11):
            pub.submit(make_rec(i, 8, 4))
        seqs = []
        for _ in range(10):
            item = sub.recv(RECV_S)
            assert item is not None
            seqs.append(item[0]["seq"])
        assert seqs == list(range(seq0, seq0 + 10))
    unsubscribed = pub.stats()["unsubscribed"]
    sent = pub.stats()["sent"]
    # once the subscriber has gone (its unsubscription is read within the recheck interval), frames stop going out
    wait_until(lambda: pub.submit(make_rec(0, 8, 4)) or pub.stats()["unsubscribed"] > unsubscribed,
               "frames kept being sent after the last subscriber left")
    assert pub.stats()["sent"] < sent + 10_000


def test_a_host_name_that_does_not_resolve_is_named_as_such():
    # libzmq takes an unknown name for a network interface and said only 'No such device'
    pub = Publisher(["tcp://nohost.invalid:5555"], "cam")
    with pytest.raises(BindError, match="no such address or network interface"):
        pub.start()
    pub.close()


def test_gen_curve_keys_never_replaces_a_key_pair(tmp_path, capsys):
    # a second --gen-curve-keys into the same folder replaced the pair without a word: the old secret key gone,
    # and every subscriber holding the old public key locked out
    keys = tmp_path / "k"
    assert main(["--gen-curve-keys", str(keys)]) == 0
    before = {p.name: p.read_bytes() for p in keys.iterdir()}
    assert main(["--gen-curve-keys", str(keys)]) == 1
    assert {p.name: p.read_bytes() for p in keys.iterdir()} == before
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "already holds" in err[0] and str(keys) in err[0], err


def test_gen_curve_keys_into_an_unwritable_place_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file where a folder is expected")
    assert main(["--gen-curve-keys", str(blocker / "keys")]) == 1  # it ended with a FileExistsError traceback
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "cannot write" in err[0] and str(blocker / "keys") in err[0], err


def test_gen_curve_keys_into_an_empty_path_is_one_line_and_writes_nothing(tmp_path, monkeypatch, capsys):
    # `--gen-curve-keys "$KEYS"` with KEYS unset wrote the secret key into the current folder (Path("") is "."),
    # where a checkout or a shared folder could publish it; the node's file options refuse an empty path already
    monkeypatch.chdir(tmp_path)
    assert main(["--gen-curve-keys", ""]) == 1
    assert list(tmp_path.iterdir()) == []
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "empty" in err[0], err


def test_a_peer_sending_an_oversized_message_is_disconnected_and_the_others_keep_their_frames(publisher):
    # a subscriber only ever sends subscriptions (a topic prefix each), but the XPUB took messages of any size: a
    # peer could stream one long message into the node for as long as its heartbeats allowed (3 s, at loopback
    # speed). A raw ZMTP 3.0 peer (NULL security, socket type XSUB) declares a 1 MB message: the node hangs up on
    # reading its header, long before its first heartbeat (1 s) could
    import select
    import struct

    pub = publisher(sndhwm=1000)
    host, port = pub.bound_endpoints[0][len("tcp://"):].rsplit(":", 1)
    raw = socket.create_connection((host, int(port)), timeout=RECV_S)
    ready = b"\x05READY" + bytes([11]) + b"Socket-Type" + struct.pack(">I", 4) + b"XSUB"
    received = b""
    try:
        raw.sendall(b"\xff" + bytes(8) + b"\x7f" + bytes([3, 0]) + b"NULL".ljust(20, b"\x00") + bytes(32))
        raw.sendall(bytes([0x04, len(ready)]) + ready)
        while b"READY" not in received:  # the node's greeting and READY: the handshake is done
            part = raw.recv(4096)
            assert part, f"the node hung up during the handshake ({received!r})"
            received += part
        raw.sendall(bytes([0x02]) + struct.pack(">Q", 1 << 20) + b"\x01" + b"x" * 1000)
        closed = False
        while not closed and select.select([raw], [], [], RECV_S)[0]:  # the hang-up, or the node's first heartbeat
            try:
                part = raw.recv(65536)
            except ConnectionResetError:
                part = b""
            closed = part == b""
            assert closed or b"PING" not in part, "the node kept reading a 1 MB message from a subscriber"
    finally:
        raw.close()
    assert closed, f"the node neither hung up nor sent a heartbeat within {RECV_S} s"
    with Subscriber(pub.bound_endpoints[0], newest_only=False) as good:
        seq0 = sync(pub, good)
        pub.submit(make_rec(1))
        assert good.recv(RECV_S)[0]["seq"] == seq0
