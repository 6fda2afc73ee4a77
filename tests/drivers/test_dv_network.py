"""drivers.dv_network: the DV network input, fed by dv-processing's real NetworkWriter (tests/dv_peer.py, one process
per stream, as DV serves them) replaying the real DAVIS346 recordings."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from drivers.dv_network import DvNetworkSource, parse_dv_endpoint
from edi_live.aedat4 import Aedat4Reader
from edi_live.datatypes import Frame
from edi_live.errors import ConfigError, DeviceDisconnectedError, DeviceNotFoundError, ProtocolError, SourceError
from tests.helpers.one_shot_server import one_shot_server

pytest.importorskip("dv_processing")
REPO = Path(__file__).resolve().parents[2]
PEER = REPO / "tests" / "dv_peer.py"


class Peer:
    """One dv-processing NetworkWriter process serving one stream of a recording."""

    def __init__(self, kind: str, path: Path, *args: str) -> None:
        # events paced at 1 ms a packet, like a camera: unpaced, dv-processing's writer drops packets itself
        pace = ["--pace-s", "0.001"] if kind == "events" else []
        self.proc = subprocess.Popen([sys.executable, str(PEER), "serve", kind, str(path), *pace, *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        assert line, self.proc.stderr.read()[-2000:]
        self.port = json.loads(line)["port"]
        self.endpoint = f"tcp://127.0.0.1:{self.port}"

    def finish(self) -> None:
        try:
            self.proc.communicate(timeout=60)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()


def _drain(source: DvNetworkSource, whole: Callable[[list], bool] | None = None,
           then: Callable[[], None] | None = None) -> tuple[list, BaseException | None]:
    """The packets until the source ends; `then()` once `whole(packets)` holds (the writers may end then)."""
    packets, error = [], None
    try:
        for packet in source:
            if packet is not None:
                packets.append(packet)
                if whole is not None and then is not None and whole(packets):
                    then()
                    whole = None
    except SourceError as exc:
        error = exc
    return packets, error


def _file_frames(path: Path) -> list:
    with Aedat4Reader(path) as reader:
        return [data for stream, data in reader if stream.type == "FRME"]


def test_events_frames_and_imu_from_three_network_writers_arrive_whole_and_in_order(real_recordings, tmp_path):
    """The ordering contract while the events keep coming. It was flaky on a loaded machine: the writer paces its
    events at 1 ms a packet with sleeps, so a frame could wait past the default frame_wait_s (1 s) for them and be
    released early, by design (the next test), and the events could pause past end_grace_s (1 s) after the other
    writers had ended, which ends the source, by design too: both waits are made longer than any load. And a
    writer that ended 0.5 s after writing lost what dv-processing still buffered for a slow reader (the last 56
    of 511 event packets): the writers now end once everything has arrived."""
    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    everything = tmp_path / "received"
    peers = [Peer(kind, path, "--exit-file", str(everything)) for kind in ("events", "frames", "imu")]

    def whole(packets: list) -> bool:  # (the last frame ends after the last event: it is held until the end)
        return sum(len(p.events) for p in packets) >= 319_512 and sum(len(p.imu) for p in packets) >= 510

    try:
        source = DvNetworkSource([peers[0].endpoint, f"frames={peers[1].endpoint}", peers[2].endpoint],
                                 frame_wait_s=120.0, end_grace_s=120.0)
        with source:
            assert (source.info.width, source.info.height, source.info.label) == (346, 260, "DAVIS346_00000391")
            packets, error = _drain(source, whole, everything.touch)
    finally:
        everything.touch()
        for peer in peers:
            peer.finish()
    # the servers ending is a dropped connection: reported, after everything received was delivered
    assert isinstance(error, DeviceDisconnectedError) and "--reconnect" in str(error)
    events = np.concatenate([p.events for p in packets])
    assert len(events) == 319_512 and bool(np.all(np.diff(events["t"]) >= 0))
    assert sum(len(p.imu) for p in packets) == 510
    frames = [f for p in packets for f in p.frames]
    expected = _file_frames(path)
    assert [(f.exposure_start_us, f.exposure_end_us) for f in frames] == \
        [(f.exposure_start_us, f.exposure_end_us) for f in expected]
    assert all(np.array_equal(a.image, b.image) for a, b in zip(frames, expected))
    # the ordering contract: a frame comes no earlier than the events up to its exposure end
    seen_to = -1
    for p in packets:
        if len(p.events):
            seen_to = int(p.events["t"][-1])
        for f in p.frames:
            assert seen_to >= f.exposure_end_us or seen_to == int(events["t"][-1])
    assert source.status().events == 319_512 and source.status().dropped_events == 0


def test_a_frame_waits_frame_wait_s_for_stalled_events_then_goes_out(real_recordings, tmp_path):
    """Events that stall (DV sends no event packet: a still scene, a stopped output) hold a frame back for
    frame_wait_s at most: here the events writer starts only once the frame has come out on its own."""
    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    go = tmp_path / "go"
    peers = [Peer("events", path, "--go-file", str(go)), Peer("frames", path)]
    try:
        source = DvNetworkSource([peers[0].endpoint, f"frames={peers[1].endpoint}"], frame_wait_s=0.2)
        with source:
            packets = iter(source)
            first = None
            while first is None:
                packet = next(packets)
                if packet is not None:
                    assert len(packet.events) == 0  # nothing was written yet
                    first = packet if packet.frames else None
            go.touch()
            events = 0
            try:
                for packet in packets:
                    events += 0 if packet is None else len(packet.events)
            except DeviceDisconnectedError:
                pass  # the writers ending
    finally:
        go.touch()
        for peer in peers:
            peer.finish()
    assert first.frames[0].exposure_end_us == _file_frames(path)[0].exposure_end_us
    assert events == 319_512  # and the events still all arrive after it


def test_connection_refused_is_one_clear_line():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nothing listens here once closed
    with pytest.raises(DeviceNotFoundError, match="connection refused") as err:
        with DvNetworkSource([f"tcp://127.0.0.1:{port}"]):
            pass
    assert "\n" not in str(err.value) and f"tcp://127.0.0.1:{port}" in str(err.value)


def test_a_server_that_sends_nothing_is_one_readable_line():
    # e.g. --dv-input pointed at edi-live's own ZeroMQ port: it said "sent no the stream header"
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(1)
        endpoint = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        with pytest.raises(ProtocolError) as err:
            with DvNetworkSource([endpoint], connect_timeout_s=0.2):
                pass
    assert str(err.value).startswith(f"{endpoint} accepted the connection but did not send the stream header "
                                     "within"), str(err.value)


def test_unexpected_stream_types_are_refused(real_recordings):
    path = real_recordings["evlib_sample_davis346.aedat4"]
    imu = Peer("imu", path, "--hold-s", "3")
    try:
        with pytest.raises(ConfigError, match="no endpoint serves events"):
            with DvNetworkSource([imu.endpoint]):
                pass
        with pytest.raises(ProtocolError, match="serves imu .*not the events"):
            with DvNetworkSource([f"events={imu.endpoint}"]):
                pass
    finally:
        imu.proc.kill()
    for bad in ("tcp://127.0.0.1", "pose=tcp://127.0.0.1:1", "udp://127.0.0.1:9"):
        with pytest.raises(ConfigError, match="--dv-input must look like"):
            parse_dv_endpoint(bad)


@pytest.mark.parametrize("bad", [5, 7.0, True, None, ["tcp://127.0.0.1:7777"]])
def test_an_endpoint_that_is_not_text_is_a_usage_error(bad):
    """`dv-input = [5]` in a config file ended in "internal error: AttributeError: 'int' object has no attribute
    'partition' ... report it" (exit 1) instead of the usage error a bad endpoint string gets."""
    with pytest.raises(ConfigError, match="--dv-input must look like") as info:
        parse_dv_endpoint(bad)
    assert f"(got {bad!r})" in str(info.value) and info.value.exit_code == 2


def test_reconnect_resumes_with_a_gap_and_a_sensor_size_change_is_refused(real_recordings):
    first = Peer("events", real_recordings["evlib_sample_davis346.aedat4"])
    source = DvNetworkSource([first.endpoint], reconnect=True, retry_s=0.05)
    later, other = None, None
    with source:
        it = iter(source)
        got, deadline = 0, time.monotonic() + 30  # (the source yields None while idle: a lost event must not hang)
        while got < 6_676 and time.monotonic() < deadline:  # the whole first recording, then the server goes away
            packet = next(it)
            got += 0 if packet is None else len(packet.events)
        assert got == 6_676, f"the first recording did not arrive whole ({got} events)"
        first.finish()
        # the same endpoint comes back (a later recording: time goes on), and the stream resumes with a gap mark
        later = Peer("events", real_recordings["aestream_davis346.aedat4"], "--port", str(first.port))
        resumed, deadline = [], time.monotonic() + 30
        while sum(len(p.events) for p in resumed) < 117_667 and time.monotonic() < deadline:
            packet = next(it)
            if packet is not None:
                resumed.append(packet)
        assert sum(len(p.events) for p in resumed) == 117_667 and resumed[0].gap and source.status().gaps >= 1
        later.finish()
        # now it comes back as another sensor: that cannot be followed, and says so
        other = Peer("events", real_recordings["evlib_sample_davis346.aedat4"], "--port", str(first.port),
                     "--size", "240x180", "--hold-s", "3")
        with pytest.raises(ProtocolError, match="came back as events 240x180, it was events 346x260"):
            for _ in it:
                pass
    other.proc.kill()


def test_a_server_that_serves_its_recording_again_continues_after_the_earlier_times(real_recordings):
    """The same recording served again after a reconnect goes back in time: its events are handed on, shifted to
    continue after the first serving's, not dropped as too old (which lost all of them)."""
    path = real_recordings["evlib_sample_davis346.aedat4"]
    first = Peer("events", path)
    source = DvNetworkSource([first.endpoint], reconnect=True, retry_s=0.05)
    again = None
    with source:
        it = iter(source)
        packets: list = []
        deadline = time.monotonic() + 30  # (the source yields None while idle: without it a loss hung the suite)
        while sum(len(p.events) for p in packets) < 6_676 and time.monotonic() < deadline:
            packet = next(it)
            if packet is not None:
                packets.append(packet)
        assert sum(len(p.events) for p in packets) == 6_676, "the first serving did not arrive whole"
        first.finish()
        again = Peer("events", path, "--port", str(first.port))
        resumed: list = []
        deadline = time.monotonic() + 30
        while sum(len(p.events) for p in resumed) < 6_676 and time.monotonic() < deadline:
            packet = next(it)
            if packet is not None:
                resumed.append(packet)
        again.finish()
    t1 = np.concatenate([p.events["t"] for p in packets])
    t2 = np.concatenate([p.events["t"] for p in resumed])
    assert len(t2) == 6_676 and source.status().dropped_events == 0, (len(t2), source.status())
    assert t2[0] > t1[-1] and np.all(np.diff(t2) >= 0)
    assert np.array_equal(t2 - t2[0], t1 - t1[0])  # the same recording, its spacing kept
    assert resumed[0].gap


def test_events_and_frames_served_again_keep_their_common_clock(real_recordings):
    """Both streams of the camera served again: whichever shows the restart first, the frames keep their place
    among the events (one offset for both), and every event from the first frame's exposure on is handed on."""
    path = real_recordings["evlib_sample_davis346.aedat4"]
    expected = _file_frames(path)
    with Aedat4Reader(path) as reader:
        file_t = np.concatenate([d["t"] for s, d in reader if s.type == "EVTS"])
    peers = [Peer("events", path), Peer("frames", path)]
    source = DvNetworkSource([peers[0].endpoint, f"frames={peers[1].endpoint}"], reconnect=True, retry_s=0.05)
    with source:
        it = iter(source)

        def take() -> list:
            """Packets until all frames and the shifted last event of the recording are in."""
            got, deadline = [], time.monotonic() + 30
            while time.monotonic() < deadline:
                frames = [f for p in got for f in p.frames]
                if len(frames) == len(expected):
                    offset = frames[0].exposure_start_us - expected[0].exposure_start_us
                    if any(len(p.events) and p.events["t"][-1] >= file_t[-1] + offset for p in got):
                        break
                packet = next(it)
                if packet is not None:
                    got.append(packet)
            return got

        take()
        for peer in peers:
            peer.finish()
        peers = [Peer("events", path, "--port", str(peers[0].port)), Peer("frames", path, "--port", str(peers[1].port))]
        second = take()
        for peer in peers:
            peer.finish()
    frames = [f for p in second for f in p.frames]
    assert len(frames) == len(expected)
    offset = frames[0].exposure_start_us - expected[0].exposure_start_us
    assert [(f.exposure_start_us, f.exposure_end_us) for f in frames] == \
        [(f.exposure_start_us + offset, f.exposure_end_us + offset) for f in expected]
    events = np.concatenate([p.events["t"] for p in second])
    from_first_frame = file_t[file_t >= expected[0].exposure_start_us] + offset
    assert np.array_equal(events[events >= frames[0].exposure_start_us][:len(from_first_frame)], from_first_frame)


def test_a_consumer_that_falls_behind_costs_counted_drops_and_a_gap(real_recordings):
    peer = Peer("events", real_recordings["emlb_demo-01_davis346.aedat4"])
    source = DvNetworkSource([peer.endpoint], max_queued_events=20_000)
    with source:
        peer.proc.stdout.readline()  # {"done": ...}: everything was sent while nobody consumed
        packets, error = _drain(source)
    peer.finish()
    status = source.status()
    received = sum(len(p.events) for p in packets)
    assert status.dropped_events > 0 and received + status.dropped_events == 319_512
    assert received <= 20_000 + 2_000 and any(p.gap for p in packets)
    assert isinstance(error, DeviceDisconnectedError)


def test_colour_frames_from_a_dv_network_writer_arrive_as_bgr(tmp_path, rng):
    from edi_live.aedat4 import Aedat4Writer
    from tests.helpers.recordings import flatten, random_recording

    events, grey, _ = flatten(random_recording(rng, 346, 260, n_events=3000, n_frames=2, n_imu=0,
                                               duration_us=60_000))
    bgr = [np.ascontiguousarray(np.stack([f.image, 255 - f.image, f.image // 2], axis=2)) for f in grey]
    path = tmp_path / "colour.aedat4"
    with Aedat4Writer(path, 346, 260, camera_name="DAVIS346_00000007") as w:
        w.write_events(events)
        for f, image in zip(grey, bgr):
            w.write_frame(Frame(image, f.exposure_start_us, f.exposure_end_us))
    peers = [Peer(kind, path) for kind in ("events", "frames")]
    try:
        with DvNetworkSource([p.endpoint for p in peers]) as source:
            packets, _ = _drain(source)
    finally:
        for peer in peers:
            peer.finish()
    frames = [f for p in packets for f in p.frames]
    assert len(frames) == 2 and all(np.array_equal(f.image, image) for f, image in zip(frames, bgr))


# ---- hostile or broken servers: a plain socket server on the loopback sends exactly the bytes the test gives

def _events_header(xml: bytes | None = None) -> bytes:
    from edi_live.aedat4.writer import info_xml, io_header
    xml = xml if xml is not None else info_xml([(0, "EVTS", "events")], 32, 24, "DAVIS346_00000001", "none")
    return io_header("none", -1, xml)[0]


def _events_packets(n: int = 300) -> bytes:
    import struct

    from edi_live.aedat4.writer import events_payloads
    from edi_live.datatypes import EVENT_DTYPE
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = 1_700_000_000_000_000 + np.arange(n) * 10
    ev["x"], ev["y"], ev["p"] = np.arange(n) % 32, np.arange(n) % 24, np.arange(n) % 2 == 0
    return b"".join(struct.pack("<ii", 0, len(p)) + p for p, *_ in events_payloads(ev))


@pytest.mark.parametrize("width, height", [(0, 0), (-5, 24), (346, 0), (None, None)])
def test_a_header_without_a_sensor_size_is_the_streams_one_line_fault(width, height):
    """An events stream whose header declares no usable sensor size (sizeX/sizeY missing, 0 or negative) was
    accepted as a 0x0 sensor with its events; the node then stopped with 'sensor size must be positive (got 0x0)',
    exit 2 (a usage error), naming neither the endpoint nor the header. A replayed file is refused the same way."""
    from edi_live.aedat4.writer import info_xml
    xml = info_xml([(0, "EVTS", "events")], 32, 24, "DAVIS346_00000001", "none")
    if width is None:
        xml = xml.replace(b'<attr key="sizeX" type="int">32</attr>', b"").replace(
            b'<attr key="sizeY" type="int">24</attr>', b"")
    else:
        xml = xml.replace(b">32<", f">{width}<".encode()).replace(b">24<", f">{height}<".encode())
    with one_shot_server(_events_header(xml) + _events_packets()) as endpoint:
        with pytest.raises(ProtocolError) as err:
            with DvNetworkSource([endpoint], connect_timeout_s=2):
                pass
    message = str(err.value)
    assert "\n" not in message and endpoint in message and "sensor size" in message
    assert err.value.exit_code == 1


def test_two_streams_with_one_id_in_a_header_are_a_protocol_error():
    """An events and a frames stream both declared as id 0: the frames entry replaced the events one, and the
    node said '--dv-input: no endpoint serves events' (a usage error, exit 2) of an endpoint that declares them."""
    from edi_live.aedat4.writer import info_xml
    xml = info_xml([(0, "EVTS", "events"), (0, "FRME", "frames")], 32, 24, "DAVIS346_00000001", "none")
    with one_shot_server(_events_header(xml) + _events_packets()) as endpoint:
        with pytest.raises(ProtocolError) as err:
            with DvNetworkSource([endpoint], connect_timeout_s=2):
                pass
    assert "\n" not in str(err.value) and endpoint in str(err.value) and "id 0" in str(err.value)


def test_a_packet_announced_but_never_sent_costs_no_memory_of_its_announced_size():
    """A peer announcing a packet of almost MAX_PACKET_BYTES (8 bytes) made the reader allocate all of it before
    a byte of it arrived (and copy it at the end): 256 MB per connection for a slowloris. Memory now follows
    what arrives. The peer closes mid-packet: the events before it are kept and the end is one line."""
    import struct
    import tracemalloc

    from drivers.dv_network import MAX_PACKET_BYTES
    data = _events_header() + _events_packets() + struct.pack("<ii", 0, MAX_PACKET_BYTES - 1) + b"\0" * 1000
    tracemalloc.start()
    try:
        with one_shot_server(data) as endpoint:
            with DvNetworkSource([endpoint], connect_timeout_s=2, end_grace_s=0.2) as source:
                packets, error = _drain(source)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sum(len(p.events) for p in packets) == 300
    assert isinstance(error, DeviceDisconnectedError) and "\n" not in str(error)
    assert peak < 32 << 20, f"{peak / 2**20:.0f} MB traced"


def test_a_stop_while_a_server_stalls_inside_its_header_ends_the_opening_at_once():
    """Ctrl-C while a server had sent a header size and then nothing: the node waited out connect_timeout_s, then
    exited 1 with 'the main thread failed: _Stopped:' (an internal exception leaking). A stop now ends the opening
    within the reader's poll, and the source then yields nothing (the node ends as a stopped node does)."""
    import struct
    sent, release, opened = threading.Event(), threading.Event(), threading.Event()
    outcome: list = []
    with one_shot_server(struct.pack("<I", 500) + b"\0" * 10, sent, release) as endpoint:
        source = DvNetworkSource([endpoint], connect_timeout_s=60)

        def open_it() -> None:
            try:
                with source:
                    opened.set()
                    outcome.append(list(source))
            except BaseException as exc:  # noqa: BLE001 - the test reports it
                outcome.append(exc)

        opener = threading.Thread(target=open_it, daemon=True)
        opener.start()
        assert sent.wait(10)
        source.stop()
        opener.join(5)
        release.set()
    assert not opener.is_alive(), "the opening did not end after stop()"
    assert opened.is_set() and outcome == [[]], outcome


def test_a_header_sent_byte_by_byte_is_bounded_by_the_connect_timeout_as_a_whole():
    """Each byte of the header restarted connect_timeout_s: a peer sending one byte every few seconds held the
    node's start-up for as long as it liked (a 1 MB header: weeks). The whole header now has connect_timeout_s."""
    import struct
    header = struct.pack("<I", 500)
    done = threading.Event()
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    endpoint = f"tcp://127.0.0.1:{server.getsockname()[1]}"

    def trickle() -> None:
        with server, server.accept()[0] as conn:
            conn.sendall(header)
            while not done.wait(0.05):  # the peer's pace, well inside each wait of the reader
                conn.sendall(b"\0")

    thread = threading.Thread(target=trickle, daemon=True)
    thread.start()
    started = time.monotonic()
    try:
        with pytest.raises(ProtocolError, match="did not send the stream header within 0.5 s"):
            with DvNetworkSource([endpoint], connect_timeout_s=0.5):
                pass
    finally:
        done.set()
        thread.join(5)
    assert time.monotonic() - started < 5


def test_frames_that_arrive_faster_than_they_are_taken_are_bounded_counted_and_the_newest_kept(caplog):
    """The queue between the readers and the consumer dropped only event packets: frames (and IMU, triggers) from
    a server sending them faster than the node takes them queued without bound (a frames-only flood: all of
    them in memory). Frames beyond max_queued_frame_bytes now drop the oldest ones, counted in a warning and
    marked as a gap."""
    import struct

    from edi_live.aedat4.writer import frame_payload, info_xml
    xml = info_xml([(0, "EVTS", "events"), (1, "FRME", "frames")], 32, 24, "DAVIS346_00000001", "none")
    t0 = 1_700_000_000_000_000
    frames = b"".join(struct.pack("<ii", 1, len(p)) + p for p in (
        frame_payload(Frame(np.full((24, 32), k % 256, np.uint8), t0 + 1000 * k, t0 + 1000 * k + 10), 1)
        for k in range(400)))
    one_frame = 24 * 32
    with one_shot_server(_events_header(xml) + frames) as endpoint:
        source = DvNetworkSource([endpoint], max_queued_frame_bytes=50 * one_frame, end_grace_s=0.2)
        with source, caplog.at_level("WARNING", logger="drivers.dv_network"):
            source._feeds[0].thread.join(10)  # the reader has read everything the server sent, and its end
            assert not source._feeds[0].thread.is_alive()
            assert len(source._queue) <= 50 + 1  # the frames, and the end of the stream
            packets, error = _drain(source)
    got = [f for p in packets for f in p.frames]
    assert 0 < len(got) <= 50 and got[-1].exposure_end_us == t0 + 1000 * 399 + 10  # the newest are kept
    assert any(p.gap for p in packets) and source.status().gaps >= 1
    assert isinstance(error, DeviceDisconnectedError)
    assert any(f"{400 - len(got)} frame" in r.getMessage() for r in caplog.records), caplog.text


def test_one_header_declaring_two_streams_of_one_type_names_that_endpoint():
    """One endpoint whose header declares two IMU streams was refused with '--dv-input: two endpoints serve imu;
    give one endpoint per stream type' (a usage error, exit 2) although only one endpoint was given."""
    from edi_live.aedat4.writer import info_xml
    xml = info_xml([(0, "EVTS", "events"), (1, "IMUS", "imu"), (2, "IMUS", "imu2")], 32, 24, "DAVIS346_00000001",
                   "none")
    with one_shot_server(_events_header(xml) + _events_packets()) as endpoint:
        with pytest.raises(ProtocolError) as err:
            with DvNetworkSource([endpoint], connect_timeout_s=2):
                pass
    message = str(err.value)
    assert "\n" not in message and endpoint in message and "2 imu streams" in message and err.value.exit_code == 1


def test_a_stop_while_a_server_trickles_a_packet_ends_the_reader_at_once():
    """A peer sending a packet's body a byte at a time never let recv() time out, and the reader looked for stop()
    only on a timeout: a stop waited for __exit__'s 2 s join per such endpoint, then closed the socket under it."""
    import struct
    done = threading.Event()
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    endpoint = f"tcp://127.0.0.1:{server.getsockname()[1]}"
    started = threading.Event()

    def trickle() -> None:
        with server, server.accept()[0] as conn:
            conn.sendall(_events_header() + _events_packets() + struct.pack("<ii", 0, 1 << 20))
            started.set()
            while not done.wait(0.02):  # the peer's pace, well inside each wait of the reader
                conn.sendall(b"\0")

    thread = threading.Thread(target=trickle, daemon=True)
    thread.start()
    try:
        source = DvNetworkSource([endpoint], connect_timeout_s=2)
        with source:
            for packet in source:
                if packet is not None and len(packet.events):
                    break  # the events before the trickled packet have arrived
            assert started.wait(5)
            source.stop()
            stopping = time.monotonic()
        assert not source._feeds[0].thread.is_alive()
        assert time.monotonic() - stopping < 1.5, "the reader did not see stop() while bytes kept coming"
    finally:
        done.set()
        thread.join(5)
