"""tools/viewer.py (`python -m tools.viewer`) against a real Publisher on loopback: PNG and MP4 recording, the HTTP endpoints, the CLI
(--help, a timed run, Ctrl-C, a busy port), and the live MJPEG page in real headless Chromium."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from edi_live.datatypes import Reconstruction
from edi_live.errors import ClientError
from edi_live.publisher import Publisher
from tools import viewer
from tests.helpers.polling import wait_until

REPO = Path(__file__).resolve().parents[2]
W, H = 240, 180


def pattern(i: int) -> np.ndarray:
    """A textured test card; pixel block (0..7, 0..7) carries i so a saved frame can be matched to its source."""
    y, x = np.mgrid[0:H, 0:W]
    image = ((x * 255) // (W - 1)).astype(np.uint8)
    image[(y // 30 + x // 30) % 2 == 0] //= 3
    image[60:120, 150:210] = 255
    image[:8, :8] = i % 200
    return image


def colour_pattern(i: int) -> np.ndarray:
    """A BGR card whose three planes differ: blue is pattern(i), green its negative, red a constant 200."""
    card = pattern(i)
    return np.ascontiguousarray(np.stack([card, 255 - card, np.full_like(card, 200)], axis=2))


def rec(i: int, colour: bool = False) -> Reconstruction:
    return Reconstruction(colour_pattern(i) if colour else pattern(i), 1000 * i, "latent", 0, 0, 0, 0.2, 0.2, i)


class Feeder:
    """A Publisher fed with pattern(i) frames every period_s from a thread."""

    def __init__(self, period_s: float = 0.02, colour: bool = False) -> None:
        self.colour = colour
        self.pub = Publisher(["tcp://127.0.0.1:*"], "test-cam", sndhwm=1000, stats_interval_s=0.2,
                             stats_provider=lambda: {"events_per_s": 2.0e6, "c": 0.2})
        self.pub.start()
        self.endpoint = self.pub.bound_endpoints[0]
        self._stop = threading.Event()
        self._period_s = period_s
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        i = 0
        while not self._stop.wait(self._period_s):
            self.pub.submit(rec(i, self.colour))
            i += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.pub.close()


@pytest.fixture
def feeder():
    f = Feeder()
    yield f
    f.close()


def start_viewer(argv: list[str]) -> tuple[viewer.Viewer, threading.Thread]:
    v = viewer.Viewer(viewer.build_parser().parse_args(argv))
    thread = threading.Thread(target=v.run, daemon=True)
    thread.start()
    return v, thread


def stop_viewer(v: viewer.Viewer, thread: threading.Thread) -> None:
    v.stop.set()
    thread.join(10)
    assert not thread.is_alive(), "viewer loop did not stop"
    v.close()


def test_help_teaches():
    out = subprocess.run([sys.executable, "-m", "tools.viewer", "--help"], cwd=REPO, capture_output=True,
                         text=True, timeout=60, check=False)
    assert out.returncode == 0
    for needle in ("--mp4", "--png", "127.0.0.1:8080", "--endpoint", "examples:", "--curve-server-key"):
        assert needle in out.stdout


def test_rates_count_seq_gaps_and_status_line():
    rates = viewer.Rates()
    for seq in (5, 6, 9, 10, 20):
        rates.add(seq)
    assert rates.lost == 2 + 9 and rates.frames == 5
    rates.add(30, skipped=6)  # 9 missing, 6 of them drained by newest-only: only 3 lost
    assert rates.lost == 2 + 9 + 3
    line = viewer.status_line(rates, 3, {"frames_per_s": 100.0, "events_per_s": 1.5e6, "c": 0.2,
                                         "latency_p50_us": 350.0, "latency_p99_us": 900.0, "publish_dropped": 4})
    assert "1.50 Mev/s" in line and "p50 0.35 ms" in line and "p99 0.90 ms" in line and "lost 14" in line
    assert "node drops 4" in line
    # the node's stats message carries the total over all stages as "drops": that is what the viewer shows
    assert "node drops 9 " in viewer.status_line(rates, 0, {"drops": 9, "publish_dropped": 4}) + " "
    assert "no stats yet" in viewer.status_line(rates, 0, None)
    assert "c 0.25/0.30" in viewer.status_line(rates, 0, {"c_on": 0.25, "c_off": 0.3, "latency_p50_us": None})
    # the node's stats always carry c (the mean) beside c_on and c_off: unequal thresholds must still show
    assert "c 0.25/0.30" in viewer.status_line(rates, 0, {"c": 0.275, "c_on": 0.25, "c_off": 0.3})
    assert "c 0.20 " in viewer.status_line(rates, 0, {"c": 0.2, "c_on": 0.2, "c_off": 0.2}) + " "
    quality = viewer.status_line(rates, 0, {"pred_psnr_db": 33.26, "still_psnr_db": 29.61})
    assert "predicts next APS frame 33.3 dB (nothing moved: 29.6 dB)" in quality
    assert "predicts" not in viewer.status_line(rates, 0, {"pred_psnr_db": None})


def test_stats_values_that_are_no_finite_number_show_as_a_dash():
    # a publisher's NaN, inf or true went onto the line as 'nan Mev/s', 'c inf', 'predicts ... 1.0 dB'
    stats = {"frames_per_s": float("inf"), "events_per_s": float("nan"), "c": True, "latency_p50_us": "fast",
             "drops": float("-inf"), "pred_psnr_db": float("nan"), "still_psnr_db": 20.0}
    line = viewer.status_line(viewer.Rates(), 0, stats)
    assert "node - fps, - Mev/s, c - | latency p50 - ms p99 - ms | node drops - |" in line, line
    assert "nan" not in line.lower() and "inf" not in line and "predicts" not in line
    assert "predicts next APS frame 1.0 dB" not in viewer.status_line(viewer.Rates(), 0, {"pred_psnr_db": True})


def test_stats_that_stopped_coming_are_not_shown_as_current():
    # a node killed mid-run kept showing 'node 634.1 fps, 0.62 Mev/s' next to 'recv 0.0 fps' for ever
    rates = viewer.Rates()
    stats = {"frames_per_s": 634.1, "events_per_s": 6.2e5, "c": 0.44}
    assert "634.1 fps" in viewer.status_line(rates, 0, stats, stats_age_s=1.0)
    stale = viewer.status_line(rates, 0, stats, stats_age_s=7.4)
    assert "634.1" not in stale and "no stats from the node for 7 s" in stale, stale


def test_to_u8_scales_other_depths():
    assert viewer.to_u8(np.array([[0, 65535]], np.uint16)).tolist() == [[0, 255]]
    assert viewer.to_u8(np.array([[-3.0, 300.0, np.nan]], np.float32)).tolist() == [[0, 255, 0]]


def test_png_and_mp4_recording(feeder, tmp_path):
    png_dir, mp4 = tmp_path / "png", tmp_path / "out.mp4"
    v, thread = start_viewer(["--endpoint", feeder.endpoint, "--all", "--no-http", "--quiet",
                              "--png", str(png_dir), "--mp4", str(mp4), "--max-frames", "15"])
    thread.join(30)
    assert not thread.is_alive()
    v.close()
    pngs = sorted(png_dir.glob("frame_*.png"))
    assert len(pngs) == 15
    for path in pngs:
        saved = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(saved, pattern(int(saved[0, 0])))  # PNG is lossless
    cap = cv2.VideoCapture(str(mp4))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    cap.release()
    assert len(frames) == 15 and frames[0].shape == (H, W)
    assert np.abs(frames[-1].astype(int) - pattern(0).astype(int))[8:, 8:].mean() < 8  # lossy but the same card


def test_http_endpoints_serve_the_frame_and_stats(feeder):
    v, thread = start_viewer(["--endpoint", feeder.endpoint, "--http", "127.0.0.1:0", "--quiet"])
    try:
        assert v.url.startswith("http://127.0.0.1:")
        wait_until(lambda: v.rates.frames > 3 and v.hub.status.get("node"))
        with urllib.request.urlopen(v.url + "frame.jpg", timeout=10) as resp:
            assert resp.headers["Content-Type"] == "image/jpeg"
            jpeg = cv2.imdecode(np.frombuffer(resp.read(), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert np.abs(jpeg.astype(int) - pattern(0).astype(int))[8:, 8:].mean() < 8
        with urllib.request.urlopen(v.url + "status.json", timeout=10) as resp:
            status = json.load(resp)
        assert status["node"]["events_per_s"] == 2.0e6 and status["viewer_fps"] >= 0
        assert "2.00 Mev/s" in status["line"]
        with urllib.request.urlopen(v.url + "stream.mjpg", timeout=10) as resp:
            assert resp.headers["Content-Type"].startswith("multipart/x-mixed-replace")
            chunk = resp.read(2000)
        assert chunk.startswith(f"--{viewer.BOUNDARY}\r\nContent-Type: image/jpeg".encode())
        with urllib.request.urlopen(v.url, timeout=10) as resp:
            assert b'src="/stream.mjpg"' in resp.read()
    finally:
        stop_viewer(v, thread)


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _screenshot(url: str, tmp_path) -> Path:
    """A 900x400 headless-Chromium screenshot of the page at `url`."""
    shot = tmp_path / "shot.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}", "--window-size=900,400",
           "--hide-scrollbars", "--force-device-scale-factor=1", "--timeout=5000", url]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=50, check=False)
    assert shot.is_file(), f"chromium wrote no screenshot (exit {out.returncode}): {out.stderr[-500:]}"
    return shot


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (Debian: apt-get install -y chromium); "
                                             "tools/test.sh installs it when run as root")
def test_mjpeg_page_shows_the_frame_in_headless_chromium(feeder, tmp_path):
    v, thread = start_viewer(["--endpoint", feeder.endpoint, "--http", "127.0.0.1:0", "--quiet"])
    try:
        wait_until(lambda: v.rates.frames > 3)
        shot = _screenshot(v.url, tmp_path)
    finally:
        stop_viewer(v, thread)
    page = cv2.imread(str(shot), cv2.IMREAD_GRAYSCALE)
    assert page.shape == (400, 900)
    # the frame is scaled to the window, aspect ratio kept: it fills the height (the limiting side here), centred
    # in the area left of the counters' border line (#333)
    border = int(np.flatnonzero((np.abs(page.astype(int) - 0x33) <= 3).all(axis=0))[0])
    assert 450 < border < 800, "no counters column beside the frame"
    width = round(400 * W / H)
    left = (border - width) // 2
    shown = cv2.resize(page[:, left + 2:left + width - 2], (W, H), interpolation=cv2.INTER_AREA).astype(float)
    card = cv2.resize(pattern(0)[:, 1:-1], (W, H), interpolation=cv2.INTER_AREA).astype(float)
    assert np.corrcoef(shown[8:, 8:].ravel(), card[8:, 8:].ravel())[0, 1] > 0.95
    assert page[:, :max(left - 2, 1)].max() < 20 and page[:, left + width + 2:border - 1].max() < 20, \
        "the frame is not centred at the scaled size"
    # the counters sit beside the frame, not below it
    assert (page[:, border + 1:] > 100).sum() > 200, "no counters right of the frame"


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_the_browser_shows_a_colour_stream_in_colour(tmp_path):
    feeder = Feeder(colour=True)
    v, thread = start_viewer(["--endpoint", feeder.endpoint, "--http", "127.0.0.1:0", "--quiet"])
    try:
        wait_until(lambda: v.rates.frames > 3)
        shot = _screenshot(v.url, tmp_path)
    finally:
        stop_viewer(v, thread)
        feeder.close()
    page = cv2.imread(str(shot), cv2.IMREAD_COLOR).astype(int)
    frame_area = page[:, :450][page[:, :450].sum(axis=2) > 60]  # the shown frame (the page is black around it)
    # the card's red plane is a constant 200 and its green plane the blue plane's negative: a gray rendering
    # would have equal planes everywhere
    assert abs(np.median(frame_area[:, 2]) - 200) < 15
    assert np.mean(np.abs(frame_area[:, 1] - frame_area[:, 0])) > 40

def run_cli(args: list[str], **kwargs) -> subprocess.Popen:
    kwargs.setdefault("cwd", REPO)  # tools run as `python -m tools.viewer` from the repository root
    return subprocess.Popen([sys.executable, "-m", "tools.viewer", *args], stderr=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, **kwargs)


# SIGHUP (terminal closed) killed the viewer on the spot: an MP4 without its moov atom, none of it readable
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_cli_stop_signals_stop_cleanly_and_finalize_the_mp4(feeder, tmp_path, sig):
    mp4 = tmp_path / "live.mp4"
    proc = run_cli(["--endpoint", feeder.endpoint, "--no-http", "--mp4", str(mp4), "--all"])
    try:
        wait_until(lambda: mp4.is_file() and mp4.stat().st_size > 0, 30)
        time.sleep(0.3)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "received" in err
    cap = cv2.VideoCapture(str(mp4))
    ok, frame = cap.read()
    cap.release()
    assert ok and frame.shape[:2] == (H, W)  # a finalized, readable file


def test_cli_busy_http_port_is_one_line_error(tmp_path):
    import socket

    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))
    holder.listen(1)
    try:
        proc = run_cli(["--http", f"127.0.0.1:{holder.getsockname()[1]}", "--duration", "1"])
        _, err = proc.communicate(timeout=30)
    finally:
        holder.close()
    assert proc.returncode == 1
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "cannot serve the live page" in lines[0] and "--http" in lines[0]


def test_cli_bad_usage_exits_2():
    proc = run_cli(["--http", "nonsense"])
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "HOST:PORT" in err


def _finish(proc: subprocess.Popen, timeout_s: float = 20) -> str:
    """stderr of a viewer process that should end by itself quickly; killed (and the test fails) if not."""
    try:
        return proc.communicate(timeout=timeout_s)[1]
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate(timeout=10)
        pytest.fail("the viewer did not exit by itself")


@pytest.mark.parametrize("args,fragment", [
    (["--http", "127.0.0.1:99999"], "PORT 0-65535"),
    (["--jpeg-quality", "500"], "--jpeg-quality: expected an integer from 1 to 100"),
    (["--duration", "-1"], "--duration: expected a number"),
    (["--duration", "nan"], "--duration: expected a number"),
    (["--max-frames", "0"], "--max-frames: expected an integer >= 1"),
    (["--mp4-fps", "0", "--mp4", "x.mp4"], "--mp4-fps: expected a number"),
])
def test_cli_out_of_range_values_exit_2_without_a_traceback(args, fragment):
    proc = run_cli([*args, "--no-http", "--endpoint", "tcp://127.0.0.1:1"])
    err = _finish(proc)
    assert proc.returncode == 2 and fragment in err and "Traceback" not in err, err


@pytest.mark.parametrize("make_args,fragment", [
    (lambda tmp: ["--png", str(tmp / "file.txt" / "frames")], "cannot create the --png folder"),
    (lambda tmp: ["--mp4", str(tmp / "missing" / "x.mp4")], "cannot write --mp4"),
    (lambda tmp: ["--mp4", str(tmp)], "is a directory"),
    # OpenCV picks the container by the name's ending: .txt failed at the first frame with OpenCV's own
    # multi-line warning, and .png wrote an image sequence that no player opens, without a word
    (lambda tmp: ["--mp4", str(tmp / "x.txt")], "x.txt: the name must end in .mp4"),
    (lambda tmp: ["--mp4", str(tmp / "x.png")], "x.png: the name must end in .mp4"),
])
def test_cli_unwritable_outputs_fail_at_start_with_one_line(tmp_path, make_args, fragment):
    (tmp_path / "file.txt").write_text("a file where a folder is expected")
    proc = run_cli([*make_args(tmp_path), "--no-http", "--endpoint", "tcp://127.0.0.1:1", "--duration", "30"])
    err = _finish(proc)  # fails at start: never waits out the 30 s
    lines = [line for line in err.splitlines() if line.strip()]
    assert proc.returncode == 1 and len(lines) == 1 and fragment in lines[0], err


def test_cli_timed_run_prints_rates(feeder):
    proc = run_cli(["--endpoint", feeder.endpoint, "--no-http", "--duration", "2.5"],
                   env={**os.environ, "PYTHONUNBUFFERED": "1"})
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "recv" in err and "Mev/s" in err and "latency p50" in err


def test_status_json_answers_a_stats_map_with_binary_values():
    """Issue 15.8: a stats message holding a binary value (a hostile or foreign publisher) made /status.json
    answer with a traceback and no response."""
    import msgpack
    import zmq

    from edi_live import wire

    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    stats = {"v": 1, "events_per_s": 1.0e6, "blob": b"\x00\xff", b"raw-key": 3, "inf": float("inf"),
             "ext": msgpack.ExtType(5, b"x"), "nested": [b"\x01", {"nan": float("nan")}]}
    v, thread = start_viewer(["--endpoint", f"tcp://127.0.0.1:{port}", "--http", "127.0.0.1:0", "--quiet"])
    stop = threading.Event()

    def feed():
        i = 0
        while not stop.wait(0.02):
            pub.send_multipart(wire.encode_frame(rec(i), i, "cam"))
            pub.send_multipart([b"stats", msgpack.packb(stats, use_bin_type=True)])
            i += 1

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        wait_until(lambda: v.hub.status.get("node"))
        with urllib.request.urlopen(v.url + "status.json", timeout=10) as resp:
            assert resp.status == 200
            body = resp.read().decode()

        def no_constants(name):
            raise AssertionError(f"{name} is not JSON")

        node = json.loads(body, parse_constant=no_constants)["node"]
        assert node["blob"] == "00ff" and node[b"raw-key".hex()] == 3 and node["events_per_s"] == 1.0e6
        assert node["inf"] == "inf" and node["nested"][0] == "01" and node["ext"] == [5, "78"]
    finally:
        stop.set()
        feeder.join(5)
        stop_viewer(v, thread)
        ctx.destroy(linger=0)


def test_colour_stream_in_png_mp4_and_http(tmp_path):
    feeder = Feeder(colour=True)
    png_dir, mp4 = tmp_path / "png", tmp_path / "colour.mp4"
    try:
        v, thread = start_viewer(["--endpoint", feeder.endpoint, "--all", "--http", "127.0.0.1:0", "--quiet",
                                  "--png", str(png_dir), "--mp4", str(mp4), "--max-frames", "10"])
        wait_until(lambda: v.rates.frames > 2)
        with urllib.request.urlopen(v.url + "frame.jpg", timeout=10) as resp:  # what the browser page shows
            jpeg = cv2.imdecode(np.frombuffer(resp.read(), np.uint8), cv2.IMREAD_COLOR)
        thread.join(30)
        v.close()
    finally:
        feeder.close()
    assert np.abs(jpeg.astype(int) - colour_pattern(0).astype(int))[8:, 8:].mean() < 8  # in colour
    pngs = sorted(png_dir.glob("frame_*.png"))
    assert len(pngs) == 10
    for path in pngs:
        saved = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(saved, colour_pattern(int(saved[0, 0, 0])))  # lossless BGR
    cap = cv2.VideoCapture(str(mp4))
    ok, frame = cap.read()
    cap.release()
    assert ok and frame.shape == (H, W, 3)
    assert np.abs(frame.astype(int) - colour_pattern(0).astype(int))[8:, 8:].mean() < 10  # lossy, same colours


@pytest.fixture
def raw_pub():
    """A bare PUB socket the test writes message parts to (a hostile or foreign publisher), and its endpoint."""
    import zmq

    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    yield pub, f"tcp://127.0.0.1:{port}"
    ctx.destroy(linger=0)


def joined_viewer(pub, argv: list[str]) -> viewer.Viewer:
    """A Viewer (not running: the test calls its _step) subscribed to `pub`, with nothing queued and no frame
    counted yet."""
    from edi_live import wire

    v = viewer.Viewer(viewer.build_parser().parse_args(argv))
    deadline = time.monotonic() + 10
    while v.rates.frames == 0:  # the slow joiner: repeat frame 0 until the subscription is in place
        assert time.monotonic() < deadline, "the viewer received nothing"
        pub.send_multipart(wire.encode_frame(rec(0), 0, "cam"))
        v._step()
    while v.sub.recv(0.2) is not None:  # the repeats still queued
        pass
    v.rates.frames = 0
    return v


def step_until(v: viewer.Viewer, frames: int) -> None:
    deadline = time.monotonic() + 10
    while v.rates.frames < frames and time.monotonic() < deadline:
        v._step()


def test_frames_skipped_in_a_step_that_ended_in_a_bad_message_are_not_counted_lost(monkeypatch):
    # the Subscriber counts the frames it drained before a bad message as skipped; the viewer subtracted from a
    # seq gap only the skips of the step that showed a frame, so those frames were reported lost
    v = viewer.Viewer(viewer.build_parser().parse_args(["--endpoint", "tcp://127.0.0.1:9", "--no-http", "--quiet"]))
    script = [1, ClientError("a message of 5 parts arrived"), 5]

    def recv(timeout_s):
        item = script.pop(0)
        if isinstance(item, ClientError):
            v.sub.skipped += 3  # frames 2, 3 and 4: drained, then dropped with the bad message
            raise item
        return {"seq": item}, pattern(item)

    monkeypatch.setattr(v.sub, "recv", recv)
    try:
        for _ in range(3):
            v._step()
    finally:
        v.close()
    assert (v.rates.frames, v.bad_messages, v.rates.lost) == (2, 1, 0)


def test_a_bad_stats_message_loses_no_frame(raw_pub, tmp_path):
    """A malformed stats message read in the same step as a good frame threw that frame away: not shown, not
    counted, not saved (a hostile publisher's garbage stats cost the --mp4/--png most of the stream)."""
    from edi_live import wire

    pub, endpoint = raw_pub
    png_dir = tmp_path / "png"
    v = joined_viewer(pub, ["--endpoint", endpoint, "--no-http", "--quiet", "--all", "--png", str(png_dir)])
    try:
        for i in range(1, 6):
            pub.send_multipart(wire.encode_frame(rec(i), i, "cam"))
            pub.send_multipart([b"stats", b"\xc1 not msgpack"])
        step_until(v, 5)
    finally:
        v.close()
    assert v.rates.frames == 5 and v.bad_messages >= 1
    assert {p.name for p in png_dir.glob("frame_*.png")} >= {f"frame_{i:09d}.png" for i in range(1, 6)}


def test_a_status_stream_that_went_away_stops_the_status_not_the_recording(raw_pub, tmp_path, monkeypatch):
    """'python -m tools.viewer --mp4 x.mp4 2>&1 | head -1': the status line's BrokenPipeError ended the run at
    its second status line (41 of ~80 frames in the MP4, exit 1, a traceback)."""
    from edi_live import wire

    class ClosedPipe:
        def isatty(self) -> bool:
            return False

        def write(self, text: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            raise BrokenPipeError(32, "Broken pipe")

    pub, endpoint = raw_pub
    png_dir = tmp_path / "png"
    v = joined_viewer(pub, ["--endpoint", endpoint, "--no-http", "--all", "--png", str(png_dir)])
    monkeypatch.setattr(sys, "stderr", ClosedPipe())
    try:
        for i in range(1, 4):
            v.rates._window_start -= 2.0  # each step draws the status line (due once a second)
            pub.send_multipart(wire.encode_frame(rec(i), i, "cam"))
            step_until(v, i)
    finally:
        v.close()
    assert v.rates.frames == 3
    assert {p.name for p in png_dir.glob("frame_*.png")} >= {f"frame_{i:09d}.png" for i in range(1, 4)}


def test_a_stream_of_bad_messages_is_counted_not_logged_line_by_line(raw_pub, caplog):
    """Each bad message was one warning line: a publisher of another protocol version at 1000 frames/s wrote 1000
    lines a second over the status line."""
    import msgpack

    pub, endpoint = raw_pub
    v = joined_viewer(pub, ["--endpoint", endpoint, "--no-http", "--quiet", "--all"])
    bad = [b"frame", msgpack.packb({"v": 99}), b""]
    with caplog.at_level("INFO", logger="edi-live-viewer"):
        try:
            for _ in range(50):
                pub.send_multipart(bad)
            deadline = time.monotonic() + 10
            while v.bad_messages < 50 and time.monotonic() < deadline:
                v._step()
        finally:
            v.close()
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert v.bad_messages == 50 and 1 <= len(warnings) <= 11, warnings
    assert "bad 50" in caplog.records[-1].getMessage()  # the closing summary has them all


def test_a_publisher_that_encrypts_is_one_error_line_not_a_silent_wait(tmp_path):
    # without --curve-server-key the viewer showed 'recv 0.0 fps | no stats yet' for ever
    from edi_live.publisher import generate_curve_keys

    _, secret = generate_curve_keys(tmp_path / "keys")
    pub = Publisher(["tcp://127.0.0.1:*"], "cam", curve_secret_key=secret)
    pub.start()
    try:
        proc = run_cli(["--endpoint", pub.bound_endpoints[0], "--no-http", "--quiet", "--duration", "60"])
        err = _finish(proc, 40)
    finally:
        pub.close()
    lines = [line for line in err.splitlines() if line.startswith("viewer: error:")]
    assert proc.returncode == 1 and len(lines) == 1 and "encrypts (CURVE" in lines[0], err


def test_the_status_line_fits_the_terminal_and_a_shrink_leaves_no_rows(raw_pub, monkeypatch):
    """At 80 columns the viewer's status line with the node's stats (~160 characters) wrapped, and every
    redraw left a row behind: the terminal filled with half lines. It is laid out in at most three rows of whole
    fields, redrawn in place, and a window shrunk while it runs (a terminal that re-wraps) keeps just those rows;
    it ends on its own rows at close."""
    from edi_live import wire
    from tests.edi_live.test_stats import _ScreenStream
    from tests.helpers.terminal import Screen

    pub, endpoint = raw_pub
    v = joined_viewer(pub, ["--endpoint", endpoint, "--no-http"])
    screen = Screen(80)
    monkeypatch.setattr(sys, "stderr", _ScreenStream(screen))
    monkeypatch.setenv("COLUMNS", "80")
    v._tty = True
    stats = {"frames_per_s": 640.0, "events_per_s": 630_000.0, "c": 0.44, "c_on": 0.44, "c_off": 0.44,
             "latency_p50_us": 490.0, "latency_p99_us": 5110.0, "drops": 0, "pred_psnr_db": 33.4,
             "still_psnr_db": 30.1}
    try:
        for i, columns in enumerate((80, 80, 50, 50), start=1):
            screen.resize(columns)
            monkeypatch.setenv("COLUMNS", str(columns))
            v.rates._window_start -= 2.0  # each step draws the status line (due once a second)
            pub.send_multipart(wire.encode_stats(stats))
            pub.send_multipart(wire.encode_frame(rec(i), i, "cam"))
            step_until(v, i)
            rows = screen.text()
            assert 1 <= len(rows) <= 3 and all(len(r) <= columns - 1 for r in rows), (columns, rows)
            assert rows[0].startswith("recv") and len(viewer.status_line(v.rates, 0, stats)) > 100
            assert "33.4" in " ".join(rows) or columns < 80, rows  # the prediction, at the line's end, is shown
    finally:
        v.close()
    assert rows[0].startswith("recv") and (screen.y, screen.x) == (len(screen.text()), 0)
