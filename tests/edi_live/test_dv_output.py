"""edi_live.dv_output: the AEDAT4-over-TCP server, checked against dv-processing 2.0.4 (the reference peer).

The protocol is compared with what dv-processing's own NetworkWriter sends (captured from a real one on
loopback), and the stream is consumed by dv-processing's NetworkReader in a separate process (tests/dv_peer.py).
"""

from __future__ import annotations

import json
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from edi_live.aedat4.reader import Aedat4Reader
from edi_live.datatypes import EVENT_DTYPE, Packet, Reconstruction
from edi_live.dv_output import DvOutput, parse_tcp_endpoint
from edi_live.errors import BindError, ConfigError
from tests.helpers.polling import wait_until

dv = pytest.importorskip("dv_processing")
PEER = Path(__file__).resolve().parents[1] / "dv_peer.py"
T0 = 1_700_000_000_000_000


def _rec(t_us: int, value: int, w: int = 346, h: int = 260) -> Reconstruction:
    img = np.full((h, w), value, np.uint8)
    img[0, :value] = 255  # a pixel pattern that tells frames apart
    return Reconstruction(img, t_us, "latent", t_us, t_us, t_us, 0.2, 0.2, 10)


def _recv_stream(sock: socket.socket, packets: int, timeout_s: float = 5.0) -> tuple[bytes, list[tuple[int, bytes]]]:
    """(IOHeader bytes, [(stream id, payload)]) read from a raw socket."""
    sock.settimeout(timeout_s)
    buf = b""

    def need(n: int) -> None:
        nonlocal buf
        while len(buf) < n:
            chunk = sock.recv(1 << 20)
            assert chunk, "stream ended early"
            buf += chunk

    need(4)
    hlen = 4 + struct.unpack_from("<I", buf)[0]
    need(hlen)
    header, pos, out = buf[:hlen], hlen, []
    for _ in range(packets):
        need(pos + 8)
        sid, size = struct.unpack_from("<ii", buf, pos)
        need(pos + 8 + size)
        out.append((sid, buf[pos + 8:pos + 8 + size]))
        pos += 8 + size
    return header, out


def _reference_stream(kind: str) -> tuple[bytes, list[tuple[int, bytes]]]:
    """What dv-processing's NetworkWriter sends for one frame or one event batch."""
    if kind == "frames":
        stream = dv.io.Stream.FrameStream(0, "frames", "DAVIS346_00000391", (346, 260))
    else:
        stream = dv.io.Stream.EventStream(0, "events", "DAVIS346_00000391", (346, 260))
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    writer = dv.io.NetworkWriter("127.0.0.1", port, stream)
    try:
        with socket.create_connection(("127.0.0.1", port)) as sock:
            wait_until(lambda: writer.getClientCount() == 1)
            if kind == "frames":
                writer.writeFrame(dv.Frame(T0, np.full((260, 346), 7, np.uint8)))
            else:
                store = dv.EventStore()
                for i in range(5):
                    store.push_back(T0 + i, 10 + i, 20, True)
                writer.writeEvents(store)
            got = _recv_stream(sock, 1)
        # dv-processing 2.0.4's NetworkWriter hangs in its destructor when a client has just gone: let it notice
        wait_until(lambda: writer.getClientCount() == 0)
        return got
    finally:
        del writer


@pytest.mark.parametrize("kind", ["frames", "events"])
def test_the_stream_is_laid_out_like_dv_processings_network_writer(kind):
    ref_header, ref_packets = _reference_stream(kind)
    with DvOutput("tcp://127.0.0.1:0", kind, 346, 260, camera_name="DAVIS346_00000391") as out:
        host, port = parse_tcp_endpoint(out.bound_endpoint)
        with socket.create_connection((host, port)) as sock:
            wait_until(lambda: out.client_count() == 1)
            if kind == "frames":
                out.submit(_rec(T0, 7))
            else:
                ev = np.zeros(5, EVENT_DTYPE)
                ev["t"], ev["x"], ev["y"], ev["p"] = T0 + np.arange(5), 10 + np.arange(5), 20, True
                out.submit(Packet(events=ev))
            header, packets = _recv_stream(sock, 1)
    ref = Aedat4Reader.from_stream_header(ref_header, "reference")
    ours = Aedat4Reader.from_stream_header(header, "ours")
    assert (ours.compression, ours.data_table_position) == (ref.compression, ref.data_table_position) == ("none", -1)
    strip = lambda s: (s.id, s.type, s.name, s.width, s.height, s.source)  # noqa: E731
    assert [strip(s) for s in ours.streams] == [strip(s) for s in ref.streams]
    assert [sid for sid, _ in packets] == [sid for sid, _ in ref_packets] == [0]
    ours_data = ours.decode_payload(ours.streams[0], 0, packets[0][1])
    ref_data = ref.decode_payload(ref.streams[0], 0, ref_packets[0][1])
    if kind == "frames":
        assert ours_data.image.shape == ref_data.image.shape and ours_data.exposure_start_us == T0
    else:
        assert np.array_equal(ours_data, ref_data)


def _reader(port: int, n: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(PEER), "read", "127.0.0.1", str(port), str(n)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _lines(proc: subprocess.Popen) -> list[dict]:
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err[-2000:]
    return [json.loads(line) for line in out.splitlines()]


def test_dv_processing_network_reader_gets_the_frames_and_a_reconnecting_client_resumes():
    # hold_s=0: every frame goes out as it comes (the ordering stage is tested below)
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, camera_name="DAVIS346_00000391", hold_s=0) as out:
        port = parse_tcp_endpoint(out.bound_endpoint)[1]
        first = _reader(port, 3)
        wait_until(lambda: out.client_count() == 1, 30)
        times = [T0 + 1000, T0 + 2000, T0 + 1500, T0 + 3000]  # the third goes back in time: skipped
        for k, t in enumerate(times):
            out.submit(_rec(t, k + 1))
            wait_until(lambda: out.stats()["dv_frames_sent"] + out.stats()["dv_frames_late"] == k + 1)
        lines = _lines(first)
        assert lines[0] == {"camera": "DAVIS346_00000391", "frames": True, "events": False,
                            "resolution": [346, 260]}
        frames = lines[1:]
        assert [f["t"] for f in frames] == [T0 + 1000, T0 + 2000, T0 + 3000]
        assert all(f["shape"] == [260, 346] and f["source"] == "RECONSTRUCTION" and f["exposure_us"] == 0
                   for f in frames)
        assert [f["pixel_sum"] for f in frames] == [int(_rec(0, v).image.sum()) for v in (1, 2, 4)]
        wait_until(lambda: out.client_count() == 0)  # the reader exited: the server noticed and carries on
        out.submit(_rec(T0 + 4000, 5))  # nobody listening: nothing blocks, nothing breaks
        second = _reader(port, 2)
        wait_until(lambda: out.client_count() == 1, 30)
        out.submit(_rec(T0 + 5000, 6))
        out.submit(_rec(T0 + 6000, 7))
        lines = _lines(second)
        assert lines[0]["camera"] == "DAVIS346_00000391"
        assert [f["t"] for f in lines[1:]] == [T0 + 5000, T0 + 6000]
        assert out.stats()["dv_frames_late"] == 1 and out.stats()["dv_frames_connections"] == 2


def _keyframe(f_us: int, value: int) -> Reconstruction:
    img = np.full((260, 346), value, np.uint8)
    img[0, :value] = 255
    return Reconstruction(img, f_us, "deblurred", f_us, f_us - 500, f_us + 500, 0.2, 0.2, 10)


def _latent(t_us: int, ref_us: int, value: int) -> Reconstruction:
    img = np.full((260, 346), value, np.uint8)
    img[0, :value] = 255
    return Reconstruction(img, t_us, "latent", ref_us, ref_us - 500, ref_us + 500, 0.2, 0.2, 10)


def test_a_deblurred_keyframe_that_comes_after_newer_latent_frames_reaches_dv_clients_in_time_order():
    """Causal mode emits an APS frame's deblurred frame (t = f) after latent frames newer than f, streamed from the
    previous reference meanwhile. The DV stream must stay in time order, and used to skip such keyframes: 138 of 148
    deblurred frames of a looped real recording never reached a DV client. dv-processing's NetworkReader is the
    client; a long hold makes the order stage release frames only when no older frame can still come (here: once
    f1 is out, frames a quarter period short of the next expected keyframe)."""
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, hold_s=600) as out:
        reader = _reader(parse_tcp_endpoint(out.bound_endpoint)[1], 7)
        wait_until(lambda: out.client_count() == 1, 30)
        f0, f1 = T0, T0 + 20_000
        emitted = [_keyframe(f0, 1), _latent(f0 + 5_000, f0, 2), _latent(f1 + 2_000, f0, 3),
                   _latent(f1 + 4_000, f0, 4),  # newer than f1, from f0: the copy streams while f1 is deblurred
                   _keyframe(f1, 5), _latent(f1 + 6_000, f1, 6), _latent(f1 + 8_000, f1, 7)]
        for rec in emitted:
            out.submit(rec)
        frames = _lines(reader)[1:]
        expected = sorted(emitted, key=lambda r: r.t_us)  # the oracle: the emitted frames sorted by time
        assert [f["t"] for f in frames] == [r.t_us for r in expected]
        assert [f["pixel_sum"] for f in frames] == [int(r.image.sum()) for r in expected]
        assert out.stats()["dv_frames_late"] == 0 and out.stats()["dv_frames_sent"] == 7


def test_a_held_frame_goes_out_once_its_hold_ends_and_an_older_one_after_that_is_late():
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, hold_s=0.05) as out:
        reader = _reader(parse_tcp_endpoint(out.bound_endpoint)[1], 2)
        wait_until(lambda: out.client_count() == 1, 30)
        out.submit(_latent(T0 + 1_000, T0, 1))  # the newest frame: nothing releases it but the end of its hold
        wait_until(lambda: out.stats()["dv_frames_sent"] == 1, 30)
        out.submit(_keyframe(T0 + 500, 2))  # older than a frame already sent: skipped, counted
        out.submit(_latent(T0 + 2_000, T0, 3))
        frames = _lines(reader)[1:]
        assert [f["t"] for f in frames] == [T0 + 1_000, T0 + 2_000]
        assert out.stats()["dv_frames_late"] == 1


def test_dv_processing_network_reader_gets_the_passed_through_events(rng):
    with DvOutput("tcp://127.0.0.1:0", "events", 346, 260, camera_name="DAVIS346_00000391") as out:
        proc = _reader(parse_tcp_endpoint(out.bound_endpoint)[1], 3)
        wait_until(lambda: out.client_count() == 1, 30)
        sent = []
        for k in range(3):
            ev = np.zeros(100, EVENT_DTYPE)
            ev["t"] = T0 + k * 1000 + np.arange(100)
            ev["x"], ev["y"] = rng.integers(0, 346, 100), rng.integers(0, 260, 100)
            out.submit(Packet(events=ev))
            sent.append({"n": 100, "t0": int(ev["t"][0]), "t1": int(ev["t"][-1]), "xsum": int(ev["x"].sum())})
        lines = _lines(proc)
        assert lines[0]["events"] is True and lines[0]["resolution"] == [346, 260]
        assert lines[1:] == sent


def test_a_client_that_never_reads_costs_drops_not_stalls():
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, client_queue=4, hold_s=0) as out:
        host, port = parse_tcp_endpoint(out.bound_endpoint)
        dead = socket.create_connection((host, port))
        dead.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        wait_until(lambda: out.client_count() == 1)
        start = time.monotonic()
        for k in range(400):  # 36 MB of frames into a client that reads nothing
            out.submit(_rec(T0 + k, k % 200))
        assert time.monotonic() - start < 2.0, "submit() must never wait for a client"
        wait_until(lambda: out.pending() == 0)
        assert out.stats()["dv_frames_dropped"] > 200
        live = socket.create_connection((host, port))  # a healthy client meanwhile gets the newest frames
        wait_until(lambda: out.client_count() == 2)
        out.submit(_rec(T0 + 10_000, 9))
        header, packets = _recv_stream(live, 1)
        reader = Aedat4Reader.from_stream_header(header, "live client")
        assert reader.decode_payload(reader.streams[0], 0, packets[0][1]).exposure_start_us == T0 + 10_000
        dead.close()
        live.close()
        wait_until(lambda: out.client_count() == 0)


def test_frames_the_server_had_no_time_to_take_are_counted_and_the_newest_kept(caplog):
    out = DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, inbox=8, hold_s=0)  # not started: nothing is taken
    try:
        for k in range(20):
            out.submit(_rec(T0 + k, k))
        assert out.stats()["dv_frames_dropped"] == 12 and out.pending() == 8
        caplog.set_level("INFO", logger="edi_live.dv_output")
        out.close()
        assert "12 dropped before encoding (the server fell behind)" in caplog.text
        assert "0 dropped for slow clients" in caplog.text
    finally:
        out.close()


def test_bind_errors_are_one_line_and_endpoints_are_checked():
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    try:
        out = DvOutput(f"tcp://127.0.0.1:{holder.getsockname()[1]}", "frames", 8, 8)
        with pytest.raises(BindError, match="address already in use") as err:
            out.start()
        assert "\n" not in str(err.value)
        out.close()
    finally:
        holder.close()
    for bad in ("127.0.0.1:7777", "udp://127.0.0.1:1", "tcp://127.0.0.1", "tcp://:80"):
        with pytest.raises(ConfigError, match="tcp://HOST:PORT"):
            parse_tcp_endpoint(bad)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_cli_takes_dv_input_and_serves_dv_output_and_out_is_finalised(real_recordings, tmp_path):
    """DV in (two real NetworkWriters) -> edi-live -> DV out (a real NetworkReader) and --out, end to end."""
    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    go = tmp_path / "go"
    peers = {}
    for kind, pace in (("events", ["--pace-s", "0.001"]), ("frames", [])):
        proc = subprocess.Popen([sys.executable, str(PEER), "serve", kind, str(path), "--go-file", str(go), *pace],
                                stdout=subprocess.PIPE, text=True)
        peers[kind] = (proc, json.loads(proc.stdout.readline())["port"])
    port = _free_port()
    out = tmp_path / "sharp.aedat4"
    cli = subprocess.Popen([sys.executable, "-m", "edi_live", "--dv-input", f"tcp://127.0.0.1:{peers['events'][1]}",
                            "--dv-input", f"tcp://127.0.0.1:{peers['frames'][1]}", "--dv-output",
                            f"tcp://127.0.0.1:{port}", "--no-publish", "--out", str(out), "--every", "5000"],
                           cwd=Path(__file__).resolve().parents[2], stderr=subprocess.PIPE, text=True)
    try:
        for line in cli.stderr:
            if "serving DV frames on" in line:
                break
        reader = _reader(port, 5)
        assert json.loads(reader.stdout.readline())["camera"] == "DAVIS346_00000391"
        go.touch()  # the DV servers start streaming now that every client is connected
        frames = [json.loads(line) for line in reader.communicate(timeout=60)[0].splitlines()]
        err = cli.communicate(timeout=60)[1]
    finally:
        for proc in [cli] + [p for p, _ in peers.values()]:
            if proc.poll() is None:
                proc.kill()
    # the DV servers went away: exit 1 with one error line, after everything received was processed
    assert cli.returncode == 1, err[-3000:]
    errors = [line for line in err.splitlines() if line.startswith("edi-live: error:")]
    assert len(errors) == 1 and "ended" in errors[0]
    assert "319512 events" in err
    assert len(frames) == 5 and all(f["shape"] == [260, 346] and f["source"] == "RECONSTRUCTION" for f in frames)
    ts = [f["t"] for f in frames]
    assert ts == sorted(ts) and 1643243628737093 <= ts[0] <= 1643243629248083
    with Aedat4Reader(out) as reader:  # finalised: the data table is there
        assert reader.data_table() is not None
        assert sum(1 for s, _ in reader if s.type == "FRME") >= 5


def test_colour_reconstructions_reach_dv_processing_as_colour_frames():
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, camera_name="DAVIS346_00000391") as out:
        reader = _reader(parse_tcp_endpoint(out.bound_endpoint)[1], 1)
        wait_until(lambda: out.client_count() == 1, 30)
        bgr = np.zeros((260, 346, 3), np.uint8)
        bgr[..., 0], bgr[..., 1], bgr[..., 2] = 1, 2, 3  # B, G, R
        out.submit(Reconstruction(bgr, T0, "latent", T0, T0, T0, 0.2, 0.2, 10))
        (frame,) = _lines(reader)[1:]
        assert frame["shape"] == [260, 346, 3] and frame["pixel_sum"] == 6 * 260 * 346


def test_a_flood_of_connections_is_logged_a_few_lines_then_counted(caplog):
    # a client connecting and leaving in a loop wrote two log lines per connection (7554 lines in 4 s), burying
    # the node's status line
    out = DvOutput("tcp://127.0.0.1:0", "frames", 346, 260)
    out.start()
    with caplog.at_level("INFO", logger="edi_live.dv_output"):
        try:
            host, port = parse_tcp_endpoint(out.bound_endpoint)
            for _ in range(60):
                socket.create_connection((host, port)).close()
            wait_until(lambda: out.connections == 60 and out.client_count() == 0)
        finally:
            out.close()
    lines = [r.getMessage() for r in caplog.records if "DV client" in r.getMessage()]
    assert 1 <= len(lines) <= 25, len(lines)
    assert "60 client connection(s)" in caplog.records[-1].getMessage()  # the closing line counts them all


def test_an_error_that_accept_passes_on_from_a_client_costs_that_client_only(monkeypatch):
    """Linux's accept() hands a connection's pending network error to the server (ECONNABORTED, EPROTO,
    EHOSTUNREACH, ... 'treat them like EAGAIN', accept(2)); such an error ended the server thread, and with it
    the node ('dv-output-frames failed: ...'), for one client that went wrong while it connected."""
    real_accept = socket.socket.accept
    failed = []

    def accept_failing_once(self):
        if not failed:
            failed.append(True)
            raise ConnectionAbortedError(103, "Software caused connection abort")
        return real_accept(self)

    monkeypatch.setattr(socket.socket, "accept", accept_failing_once)
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, hold_s=0) as out:
        host, port = parse_tcp_endpoint(out.bound_endpoint)
        with socket.create_connection((host, port)) as client:
            wait_until(lambda: out.client_count() == 1 or out.error is not None)
            assert out.error is None and failed
            out.submit(_rec(T0, 5))
            _, packets = _recv_stream(client, 1)
        assert len(packets) == 1


def test_a_client_that_sends_data_is_dropped_and_the_others_keep_their_frames():
    with DvOutput("tcp://127.0.0.1:0", "frames", 346, 260, hold_s=0) as out:
        host, port = parse_tcp_endpoint(out.bound_endpoint)
        with socket.create_connection((host, port)) as good, socket.create_connection((host, port)) as bad:
            wait_until(lambda: out.client_count() == 2)
            bad.sendall(b"GET / HTTP/1.1\r\n\r\n" + bytes(range(256)) * 64)
            wait_until(lambda: out.client_count() == 1)
            for k in range(3):
                out.submit(_rec(T0 + k, k))
            _, packets = _recv_stream(good, 3)
        assert len(packets) == 3 and out.error is None
