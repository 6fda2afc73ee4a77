"""A real replay node end to end: ReplaySource -> ring -> EdiWorker (real EdiReconstructor) -> Publisher -> SUB.

Oracles: the recording itself (resolution, time range, number of APS frames), the wire contract (seq +1 per
frame message, kinds), dv-processing reopening the --out file. Every wait has a timeout.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
import time
from pathlib import Path

import dv_processing as dv
import numpy as np
import pytest

from edi_live.config import NodeConfig
from edi_live.errors import BindError, NodeError, RecordingError
from edi_live.node import Node, default_reconstructor
from tests.edi_live.test_worker import StandIn
from tools.stream_harness import GatedSource  # holds the first packet until a subscriber joined

DEMO = "emlb_demo-01_davis346.aedat4"  # 0.51 s, 13 APS frames, 346x260, motion blur


def real_reconstructor(width, height, edi):
    return default_reconstructor(width, height, edi)


def replay(path, **options):
    import drivers

    return drivers.open_source("replay", path=str(path), **options)


def start_in_thread(node: Node):
    result = {}

    def target():
        try:
            result["stats"] = node.run()
        except BaseException as exc:  # handed to the test thread
            result["error"] = exc

    thread = threading.Thread(target=target, name="test-node-run", daemon=True)
    thread.start()
    return thread, result


def test_replay_node_streams_deblurred_and_latent_frames_then_stops_cleanly(real_recordings):
    from edi_live.client import Subscriber

    path = real_recordings[DEMO]
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 1, "every": 2000,
                                   "publish": ["tcp://127.0.0.1:*"], "stats_interval_s": 0.2})
    gate = threading.Event()
    node = Node(cfg, GatedSource(replay(path, speed=1), gate), reconstructor_factory=real_reconstructor)
    thread, result = start_in_thread(node)
    assert node.started.wait(20), result.get("error")
    endpoint = node.bound_endpoints[0]
    headers = []
    with Subscriber(endpoint, newest_only=False, rcvhwm=0, max_bytes=1 << 20) as sub:
        assert sub.recv_stats(timeout_s=10) is not None, "no stats message: the subscription never became live"
        gate.set()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # until the node has stopped and nothing more comes
            got = sub.recv(timeout_s=0.5)
            if got is None:
                if not thread.is_alive():
                    break
                continue  # a loaded machine may pause the stream: the end is the node's, not a silence
            header, image = got
            headers.append(header)
            assert image.shape == (260, 346) and image.dtype == np.uint8
        stats = sub.recv_stats(timeout_s=1) or sub.last_stats
    thread.join(20)
    assert not thread.is_alive(), "the node did not stop at the end of the recording"
    assert "error" not in result, result.get("error")
    seqs = [h["seq"] for h in headers]
    assert all(b > a for a, b in zip(seqs, seqs[1:])), "seq increases"
    kinds = {h["kind"] for h in headers}
    assert kinds == {"deblurred", "latent"}
    t0, t1 = 1643243628737093, 1643243629248083  # the recording's event time range (its README)
    # a deblurred frame is stamped at its mid-exposure in the event clock (APS clock + the offset in use): the
    # last one may lie past the last event by up to that offset
    offset = result["stats"]["clock_offset_us"]
    assert 0 <= offset <= 8000
    assert all(t0 <= h["t"] <= t1 for h in headers if h["kind"] == "latent")
    assert all(t0 <= h["t"] <= t1 + offset for h in headers)
    assert all(h["ref_t"] <= h["t"] for h in headers if h["kind"] == "latent")  # causal mode
    final = result["stats"]
    assert len(headers) >= final["frames_sent"] * 0.9
    assert final["aps_frames_in"] == 13
    assert final["events_processed"] == 319_512  # lossless replay: every event of the file
    assert final["drops"] == 0
    for key in ("events_per_s", "frames_per_s", "c_on", "c_off", "reestimations", "drops", "ring_occupancy"):
        assert key in stats, key
    leftovers = [t.name for t in threading.enumerate() if t.name in ("pump", "edi-worker", "publisher")]
    assert leftovers == []


def test_truncated_recording_delivers_frames_before_the_fault_and_finalises_out(real_recordings, tmp_path):
    data = real_recordings[DEMO].read_bytes()
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    out = tmp_path / "sharp.aedat4"
    cfg = NodeConfig.from_options({"replay": str(cut), "speed": 0, "every": 2000, "no_publish": True,
                                   "out": str(out)})
    node = Node(cfg, replay(cut, speed=0), reconstructor_factory=real_reconstructor)
    with pytest.raises(RecordingError) as info:
        node.run()
    assert "cut.aedat4" in str(info.value) and "\n" not in str(info.value)
    written = node.final_stats["out_frames"]
    assert written > 0 and node.final_stats["aps_frames_in"] >= 1
    rec = dv.io.MonoCameraRecording(str(out))
    times = []
    while (frame := rec.getNextFrame()) is not None:
        times.append(frame.timestamp)
    assert len(times) == written and times == sorted(times)


class LossySource(GatedSource):
    """A replay (its gate open) whose status reports raw USB bytes lost, as a live DavisSource does when its reader
    falls behind."""

    def status(self):
        return dataclasses.replace(super().status(), dropped_bytes=4096, gaps=1)


def test_raw_data_a_source_lost_reaches_subscribers_and_the_summary(real_recordings):
    from edi_live.stats import format_summary

    path = real_recordings[DEMO]
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True})
    opened = threading.Event()
    opened.set()
    node = Node(cfg, LossySource(replay(path, speed=0), opened), reconstructor_factory=lambda w, h, e: StandIn())
    node.run()
    published = node.stats_map()
    assert published["source_dropped_bytes"] == 4096 and published["source_gaps"] == 1
    assert "dropped 4096 bytes of raw data" in format_summary(node.final_stats, 1.0)


def test_duration_and_stop_end_a_looping_replay(real_recordings):
    path = real_recordings[DEMO]
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 1, "loop": True, "no_publish": True,
                                   "duration": 0.6})
    node = Node(cfg, replay(path, speed=1, loop=True), reconstructor_factory=lambda w, h, e: StandIn())
    thread, result = start_in_thread(node)
    thread.join(15)
    assert not thread.is_alive() and "error" not in result
    assert result["stats"]["events_processed"] > 0

    cfg = NodeConfig.from_options({"replay": str(path), "speed": 1, "loop": True, "no_publish": True})
    node = Node(cfg, replay(path, speed=1, loop=True), reconstructor_factory=lambda w, h, e: StandIn())
    thread, result = start_in_thread(node)
    assert node.started.wait(10)
    node.stop()
    thread.join(15)
    assert not thread.is_alive() and "error" not in result


def test_worker_failure_is_reraised_naming_the_thread(real_recordings, tmp_path):
    path = real_recordings[DEMO]
    out = tmp_path / "sharp.aedat4"
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True, "out": str(out)})
    node = Node(cfg, replay(path, speed=0), reconstructor_factory=lambda w, h, e: StandIn(fail_on_frame=True))
    with pytest.raises(NodeError, match="edi-worker thread failed: RuntimeError: boom"):
        node.run()
    assert out.stat().st_size > 0  # finalised (header + table) even though nothing was emitted


def test_bind_failure_is_raised_before_data_flows(real_recordings, tmp_path):
    path = real_recordings[DEMO]
    out = tmp_path / "sharp.aedat4"
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "publish": ["tcp://192.0.2.1:5555"],
                                   "out": str(out)})
    node = Node(cfg, replay(path, speed=0), reconstructor_factory=lambda w, h, e: StandIn())
    with pytest.raises(BindError, match="192.0.2.1"):
        node.run()
    assert node.final_stats.get("events_processed", 0) == 0
    assert not out.exists(), "no file is created when the node cannot start"


def test_record_writes_the_input_as_received(real_recordings, tmp_path):
    from drivers.replay import merged_packets

    path = real_recordings["evlib_sample_davis346.aedat4"]
    raw = tmp_path / "raw.aedat4"
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True, "record": str(raw)})
    stats = Node(cfg, replay(path, speed=0), reconstructor_factory=lambda w, h, e: StandIn()).run()
    original = [p for p in merged_packets(path)]
    again = [p for p in merged_packets(raw)]  # the recording replays
    n = sum(len(p.events) for p in original)
    assert stats["record_events"] == n == sum(len(p.events) for p in again)
    assert sum(len(p.frames) for p in again) == sum(len(p.frames) for p in original)
    t_a = np.concatenate([p.events["t"] for p in original])
    t_b = np.concatenate([p.events["t"] for p in again])
    np.testing.assert_array_equal(t_a, t_b)


class BurstSource:
    """A live-like source: packets as fast as the pump takes them (it must never be blocked), then the end."""

    def __init__(self, packets, width=8, height=8):
        from edi_live.datatypes import SourceInfo, SourceStatus

        self.packets, self.info, self._status = packets, SourceInfo(width, height, "burst", kind="usb"), SourceStatus()
        self.blocked_s = 0.0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        pass

    def stop(self):
        pass

    def status(self):
        return self._status

    def __iter__(self):
        import time

        for p in self.packets:
            t = time.monotonic()
            yield p
            self.blocked_s = max(self.blocked_s, time.monotonic() - t)


class SlowStandIn(StandIn):
    def on_events(self, events, arrival_ns=0):
        import time

        time.sleep(0.002)
        super().on_events(events, arrival_ns)


def test_live_overflow_drops_oldest_counts_every_event_and_never_blocks_the_source():
    from edi_live.datatypes import EVENT_DTYPE, Frame, Packet

    n_packets, per = 200, 500
    ev = np.zeros(n_packets * per, EVENT_DTYPE)
    ev["t"] = np.arange(len(ev))
    ev["x"] = np.arange(len(ev)) % 8
    frame = Frame(np.zeros((8, 8), np.uint8), exposure_start_us=0, exposure_end_us=100)
    packets = [Packet(events=ev[k * per:(k + 1) * per], frames=[frame] if k == 0 else []) for k in range(n_packets)]
    cfg = NodeConfig.from_options({"device": "auto", "no_publish": True, "every": 100, "ring_events": 4096})
    assert cfg.ring_policy == "drop_oldest"
    source = BurstSource(packets)
    node = Node(cfg, source, reconstructor_factory=lambda w, h, e: SlowStandIn())
    stats = node.run()
    assert stats["ring_dropped_events"] > 0, "the slow worker must have lost data"
    assert stats["events_processed"] + stats["ring_dropped_events"] == len(ev), "every event processed or counted"
    assert stats["drops"] >= stats["ring_dropped_events"] and stats["worker_gaps"] >= 1
    assert stats["ring_producer_wait_s"] == 0, "the pump never waited for the worker"


def test_edi_kernels_are_warmed_up_before_the_source_starts(real_recordings):
    # Compiling/loading the numba kernels takes up to seconds; doing it after a camera started streaming would
    # stall the worker while the ring fills. The node must exercise a reconstructor before entering the source.
    order: list[str] = []

    class Recording(StandIn):
        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            order.append("on_frame")
            return super().on_frame(frame, events, arrival_ns)

    class Watched(GatedSource):
        def __enter__(self):
            order.append("source-enter")
            return super().__enter__()

    path = real_recordings["evlib_sample_davis346.aedat4"]
    cfg = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True})
    gate = threading.Event()
    gate.set()
    Node(cfg, Watched(replay(path, speed=0), gate), reconstructor_factory=lambda w, h, e: Recording()).run()
    assert "source-enter" in order and "on_frame" in order[: order.index("source-enter")]


_NO_NEW_KERNELS = r"""
import sys
from edi_live.cli import main
from edi_live.config import EdiConfig
from edi_live.node import default_reconstructor
from edi_live.warm_up import compiled_signatures, warm_up

def kernels():
    return compiled_signatures()

if __name__ == "__main__":
    fixed_c = sys.argv[3:] and float(sys.argv[4])  # "--c C": a fixed c (no c tracker)
    warm_up(default_reconstructor, EdiConfig(mode=sys.argv[2], c=fixed_c or None))
    before = kernels()
    try:  # the CLI's replay: frames decoded in the child arrive read-only; 1 ms packets give 1-event slices
        main(["--replay", sys.argv[1], "--no-publish", "--speed", "8", "--every", "7", "--log-level", "error",
              "--mode", sys.argv[2]] + sys.argv[3:])
    except SystemExit as exc:
        assert not exc.code, exc.code
    # separate thresholds (the default estimator fits them when the data call for it) use their own kernel
    import numpy as np
    from edi_live.datatypes import EVENT_DTYPE
    from edi_live.edi import log_divisor_events
    ev = np.zeros(50, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = np.arange(50) * 10, np.arange(50) % 7, 3, np.arange(50) % 3 == 0
    log_divisor_events(ev, 8, 6, 0, 500, None, 0.25, 0.2, counts_after_f=(np.zeros(48, np.int64),
                                                                          np.zeros(48, np.int64)))
    after = kernels()
    new = {name: sorted(after[name] - before.get(name, set())) for name in after}
    print({name: sigs for name, sigs in new.items() if sigs})
"""


@pytest.mark.parametrize("name, mode, extra", [("emlb_demo-01_davis346.aedat4", "causal", []),
                                               ("evlib_sample_davis346.aedat4", "causal", []),
                                               ("emlb_demo-01_davis346.aedat4", "fused", []),
                                               ("emlb_demo-01_davis346.aedat4", "nearest", []),
                                               ("emlb_demo-01_davis346.aedat4", "causal", ["--c", "0.2"]),
                                               # exposures without events, read-only, with a fixed c (no still-scene
                                               # verdict): the per-pixel frame finish, not the smoothed one
                                               ("evlib_sample_davis346.aedat4", "causal", ["--c", "0.3"])])
def test_the_warm_up_covers_every_kernel_specialisation_a_replay_needs(real_recordings, name, mode, extra):
    """A numba kernel met with new argument types (a read-only frame, a one-event slice, an exposure without
    events) is compiled on the spot, seconds with a cold cache, stalling the worker mid-stream. After the node's
    warm-up a real replay must need no new specialisation. Run in a fresh interpreter, so that other tests' calls
    do not hide a gap. (evlib's first exposures hold no events.)"""
    # -c with the repository as the working directory: the interpreter imports this checkout's packages
    recording = str(real_recordings[name])
    done = subprocess.run([sys.executable, "-c", _NO_NEW_KERNELS, recording, mode, *extra], capture_output=True,
                          text=True, timeout=120, cwd=str(Path(__file__).resolve().parents[2]))
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "{}", f"compiled during the replay: {done.stdout[-2000:]}"


def test_a_first_run_reports_the_kernel_compile_apart_from_its_rate(real_recordings, tmp_path):
    """With a cold numba cache the warm-up compiles for seconds. The summary must report that on its own line and
    keep it out of "done in" and the event rate: the two figures add up to no more than the process's wall time,
    and the rate is the events over "done in" alone."""
    import os
    import re
    import time

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}  # nothing compiled yet
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "edi_live", "--replay", str(real_recordings[DEMO]), "--speed", "0",
                           "--no-publish", "--quality-every", "0"], capture_output=True, text=True, timeout=300,
                          env=env, cwd=str(Path(__file__).resolve().parents[2]))
    wall_s = time.monotonic() - t0
    assert done.returncode == 0, done.stderr[-2000:]
    run = re.search(r"done in ([\d.]+) s: (\d+) events \(([\d.]+)([kMG]?) ev/s\)", done.stderr)
    start = re.search(r"start-up: EDI kernels compiled or loaded in ([\d.]+) s", done.stderr)
    assert run and start, done.stderr
    run_s, events, warm_s = float(run.group(1)), int(run.group(2)), float(start.group(1))
    rate = float(run.group(3)) * {"": 1, "k": 1e3, "M": 1e6, "G": 1e9}[run.group(4)]
    assert run_s + warm_s <= wall_s
    # and while it compiled, the terminal said why nothing happened yet (a cold compile takes 15 s and more here).
    # The notice is due 2 s into the warm-up: a machine that compiles faster than that rightly prints none, and the
    # 2 s after it leave the notice's thread time to run while the compile holds the GIL
    said = "compiling the EDI kernels" in done.stderr.split("done in")[0]
    if warm_s < 2.0 or warm_s > 4.0:
        assert said == (warm_s > 4.0), (warm_s, done.stderr)
    assert rate == pytest.approx(events / run_s, rel=0.05)  # "done in" is rounded to 10 ms


_NO_NEW_COLOUR_KERNELS = r"""
import numpy as np
from edi_live.colour import demosaic
from edi_live.config import EdiConfig
from edi_live.node import default_reconstructor
from edi_live.warm_up import compiled_signatures, warm_up

warm_up(default_reconstructor, EdiConfig())
before = compiled_signatures()
display = np.full((260, 346), 90, np.uint8)  # the latent display, as the reconstructor demosaics it
decoded = display.copy()
decoded.setflags(write=False)  # an APS frame decoded in the replay's child, as the prediction figure shows it
for pattern in ("RGGB", "GBRG"):
    demosaic(display, pattern)
    demosaic(decoded, pattern)
after = compiled_signatures()
print({name: sorted(after[name] - before.get(name, set())) for name in after if after[name] - before.get(name, set())})
"""


def test_the_warm_up_covers_the_colour_demosaic():
    """A colour source demosaics every frame it emits with a compiled kernel: the warm-up must have compiled (or
    loaded) it for the display and for read-only decoded frames, or the first colour frame stalls the stream."""
    done = subprocess.run([sys.executable, "-c", _NO_NEW_COLOUR_KERNELS], capture_output=True, text=True,
                          timeout=120, cwd=str(Path(__file__).resolve().parents[2]))
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "{}", f"compiled after the warm-up: {done.stdout[-2000:]}"
