"""The `noise` mode of tools/bench_stream.py and its scene: a still camera with background noise events and APS
frames (noisy_scene, cut into camera-like packets by scene_packets, cached as a recording by noise_recording); the
node's CPU on it, in this process against the count-only policy or A/B against another checkout in child
processes; and the motion-onset delay (onset_delay_us), which the tests of the still-scene policy use too."""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from edi_live.config import NodeConfig
from edi_live.datatypes import Packet
from edi_live.node import Node, default_reconstructor
from tools.stream_harness import replay_source
from tools.thread_cpu import ThreadCpu

NODE_THREADS = ("edi-worker", "edi-deblur", "publisher")
"""The node's own threads on a still scene: the worker, its deblur helper (the heartbeat's deblur and the
calibration after it; one thread for the worker's life) and the publisher. Not the replay's pump, which a camera's
driver replaces."""


def noisy_scene(seconds: float, onset_s: float | None = None, noise_hz: float = 0.5, width: int = 240,
                height: int = 180, speed_px_s: float = 100.0) -> tuple[np.ndarray, list, int | None]:
    """A still camera with `noise_hz` background events per pixel and APS frames at 20 fps (simulated), and,
    with `onset_s`, the scene starts moving (`speed_px_s`) at that time. Returns (events, frames, the sensor
    time of the first event caused by motion or None)."""
    from edi_live.simulation import SceneConfig, simulate

    base = dict(width=width, height=height, noise_rate_hz=noise_hz, frame_interval_us=50_000, exposure_us=10_000,
                ground_truth=False, texture="blocks")
    still = simulate(SceneConfig(duration_s=onset_s or seconds, velocity_px_s=(0.0, 0.0), **base))
    if onset_s is None:
        return still.events, still.frames, None
    # the moving part starts from the same picture (position = v * t from its own t0), one frame period later
    moving = simulate(SceneConfig(duration_s=seconds - onset_s, velocity_px_s=(speed_px_s, 0.0),
                                  t0_us=still.config.t0_us + int(onset_s * 1e6), **base))
    events = np.concatenate([still.events, moving.events])
    return events, still.frames + moving.frames, int(moving.events["t"][~moving.is_noise][0])


def scene_packets(events: np.ndarray, frames: list, packet_us: int = 1000) -> list[Packet]:
    """1 ms packets as a camera delivers them; each APS frame in the packet that holds its exposure end."""
    t0, t1 = int(events["t"][0]), int(events["t"][-1])
    bounds = np.arange(t0, t1 + packet_us, packet_us)
    cuts = np.searchsorted(events["t"], bounds, side="right")
    packets, k = [], 0
    for i in range(len(bounds)):
        lo = cuts[i - 1] if i else 0
        mine = []
        while k < len(frames) and frames[k].exposure_end_us <= bounds[i]:
            mine.append(frames[k])
            k += 1
        packets.append(Packet(events=events[lo:cuts[i]], frames=mine, watermark_us=int(bounds[i])))
    return packets


class CountOnlyPolicy:
    """The static-scene policy before the noise test (every event counts as activity), for A/B runs."""

    def __enter__(self):
        from edi_live.activity import StaticScene

        self._saved = StaticScene.segments, StaticScene.active_since_reference, StaticScene.quiet
        StaticScene.segments = lambda scene, events: [(0, len(events), "active")] if len(events) else []
        StaticScene.active_since_reference = lambda scene: True
        StaticScene.quiet = property(lambda scene: False)  # every read as it comes, as then
        return self

    def __exit__(self, *exc):
        from edi_live.activity import StaticScene

        StaticScene.segments, StaticScene.active_since_reference, StaticScene.quiet = self._saved


def noise_recording(seconds: float, noise_hz: float = 0.5) -> Path:
    """The still noisy scene of `noisy_scene` as an AEDAT4 recording, generated once and cached."""
    cache = Path(tempfile.gettempdir()) / "edi-live-bench"
    cache.mkdir(exist_ok=True)
    path = cache / (f"noise_static_{seconds:.0f}s.aedat4" if noise_hz == 0.5 else
                    f"noise_static_{seconds:.0f}s_{noise_hz:g}hz.aedat4")
    if not path.exists():
        from edi_live.aedat4 import Aedat4Writer

        events, frames, _ = noisy_scene(seconds, noise_hz=noise_hz)
        tmp = path.with_suffix(".part")
        with Aedat4Writer(tmp, 240, 180) as writer:
            for p in scene_packets(events, frames, packet_us=10_000):
                writer.write_events(p.events)
                for f in p.frames:
                    writer.write_frame(f)
        tmp.replace(path)
    return path


def bench_noise(seconds: float, repeat: int) -> None:
    print(f"\n## static 240x180 scene with 0.5 events/s per pixel of noise, APS at 20 fps: paced replay (speed 1) "
          f"with the publisher, {seconds:.0f} s measured after 2 s; node process CPU (the decoding child, the same in "
          f"both, not counted); A/B interleaved, {repeat} repeats")

    path = noise_recording(seconds + 4)
    results: dict[str, list] = {"count-only (before)": [], "noise-aware": []}
    for _ in range(repeat):
        for name in results:
            with (CountOnlyPolicy() if name.startswith("count") else _Nothing()):
                # the policy before the noise test cut frames by event count only
                before = {"every_ms": 0} if name.startswith("count") else {}
                cfg = NodeConfig.from_options({"replay": str(path), "publish": ["tcp://127.0.0.1:*"], **before})
                node = Node(cfg, replay_source(path, 1.0))
                thread = threading.Thread(target=node.run, daemon=True)
                thread.start()
                node.started.wait(30)
                time.sleep(2.0)
                s0, cpu0, wall0 = node.stats(), time.process_time(), time.monotonic()
                with ThreadCpu() as threads:
                    time.sleep(seconds)
                cpu, wall, s1 = time.process_time() - cpu0, time.monotonic() - wall0, node.stats()
                node_cpu = sum(threads.cpu_s.get(name, 0.0) for name in NODE_THREADS)
                node.stop()
                thread.join(30)
            d = {k: s1[k] - s0[k] for k in ("frames_out", "heartbeats", "aps_frames_in", "skipped_static_deblur")}
            results[name].append((100 * node_cpu / wall, 100 * cpu / wall, (d["frames_out"] - d["heartbeats"]) / wall,
                                  d["heartbeats"] / wall, (d["aps_frames_in"] - d["skipped_static_deblur"]) / wall))
    print("| policy | worker + deblur helper + publisher, % of one core, median (min-max) | whole process (with the "
          "replay's pump) | non-heartbeat frames/s | heartbeats/s | deblurs/s |\n|---|---|---|---|---|---|")
    for name, rows in results.items():
        a = np.array(rows)
        print(f"| {name} | {np.median(a[:, 0]):.1f} ({a[:, 0].min():.1f}-{a[:, 0].max():.1f}) | "
              f"{np.median(a[:, 1]):.1f} ({a[:, 1].min():.1f}-{a[:, 1].max():.1f}) | "
              f"{np.median(a[:, 2]):.1f} | {np.median(a[:, 3]):.2f} | {np.median(a[:, 4]):.2f} |")
    print("\nmotion onset (the scene starts moving at 100 px/s after 1 s; worker alone, 1 ms packets in lockstep): "
          "first moving event -> sensor time the ring had reached when the first frame after it was sent")
    for k in range(repeat):
        delay = onset_delay_us(seed_shift=k)
        print(f"  run {k}: {delay / 1000:.1f} ms (APS frame period 50 ms)")


_NOISE_CHILD = r"""
import json, os, sys, threading, time
import drivers
from edi_live.config import NodeConfig
from edi_live.node import Node


def threads_cpu():
    tick, names, out = os.sysconf("SC_CLK_TCK"), {t.native_id: t.name for t in threading.enumerate()}, {}
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                head, rest = fh.read().rsplit(")", 1)
        except OSError:
            continue
        fields, name = rest.split(), names.get(int(tid), head.split("(", 1)[1])
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick
    return out


if __name__ == "__main__":
    path, seconds = sys.argv[1], float(sys.argv[2])
    cfg = NodeConfig.from_options({"replay": path, "publish": ["tcp://127.0.0.1:*"]})
    node = Node(cfg, drivers.open_source("replay", path=path, speed=1.0, decode_process=True))
    thread = threading.Thread(target=node.run, daemon=True)
    thread.start()
    node.started.wait(60)
    time.sleep(2.0)
    s0, t0, cpu0, wall0 = node.stats(), threads_cpu(), time.process_time(), time.monotonic()
    time.sleep(seconds)
    cpu, wall, t1, s1 = time.process_time() - cpu0, time.monotonic() - wall0, threads_cpu(), node.stats()
    node.stop()
    thread.join(30)
    d = {k: s1[k] - s0[k] for k in ("frames_out", "heartbeats", "aps_frames_in", "skipped_static_deblur")}
    by = {k: v - t0.get(k, 0.0) for k, v in t1.items()}
    print(json.dumps({"node": 100 * sum(by.get(name, 0) for name in sys.argv[3].split(",")) / wall,
                      "pump": 100 * by.get("pump", 0) / wall, "process": 100 * cpu / wall,
                      "no_pump": 100 * (cpu - by.get("pump", 0)) / wall,
                      "frames": (d["frames_out"] - d["heartbeats"]) / wall, "heartbeats": d["heartbeats"] / wall,
                      "deblurs": (d["aps_frames_in"] - d["skipped_static_deblur"]) / wall}))
"""


def bench_noise_ab(seconds: float, repeat: int, other: Path) -> None:
    """The node on the noisy still scene, this checkout against `other`, each run in its own process (which imports
    that checkout's code), in alternating order; per-thread CPU from /proc at the start and end of the window."""
    import json
    import subprocess

    here = Path(__file__).resolve().parent.parent
    path = noise_recording(seconds + 4)
    print(f"\n## A/B: static 240x180 scene, 0.5 events/s per pixel of noise, APS 20 fps, paced replay (speed 1) with "
          f"the publisher, {seconds:.0f} s after 2 s; new = {here}, old = {other}; {repeat} pairs, alternating order")
    runs: dict[str, list[dict]] = {"old": [], "new": []}
    for i in range(repeat):
        for which in (("old", "new") if i % 2 == 0 else ("new", "old")):
            out = subprocess.run([sys.executable, "-c", _NOISE_CHILD, str(path), str(seconds), ",".join(NODE_THREADS)],
                                 cwd=other if which == "old" else here, capture_output=True, text=True)
            if out.returncode != 0:
                raise SystemExit(f"{which} run failed:\n{out.stderr[-2000:]}")
            runs[which].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("| checkout | worker + deblur helper + publisher, % of one core | process without the pump | pump | "
          "whole process | non-heartbeat frames/s | heartbeats/s | deblurs/s |\n|---|---|---|---|---|---|---|---|")
    for which, rows in runs.items():
        def cell(key: str, digits: int = 1) -> str:
            v = np.array([r[key] for r in rows])
            return f"{np.median(v):.{digits}f} ({v.min():.{digits}f}-{v.max():.{digits}f})"
        print(f"| {which} | {cell('node', 2)} | {cell('no_pump', 2)} | {cell('pump')} | {cell('process')} | "
              f"{cell('frames')} | "
              f"{cell('heartbeats', 2)} | {cell('deblurs', 2)} |")
    for key in ("node", "no_pump", "process"):
        ratios = [o[key] / max(n[key], 1e-9) for o, n in zip(runs["old"], runs["new"])]
        print(f"old / new, {key} CPU per pair: median {np.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})")
    print("(thread CPU is counted in 10 ms ticks, so read the thread figures to +-0.1 % of a core)")


class _Nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None


def onset_delay_us(seed_shift: int = 0, every: int = 1000, ring=None, clock_offset_us: int | None = None) -> float:
    """Worker alone (real reconstructor) fed 1 ms packets in lockstep, as a camera delivers them: each is pushed
    once the worker has done all it will do with the ones before (EventRing.wait_consumer_idle), so what it sees
    per wake-up is what it would see live, however fast this machine is. Returns the sensor time from the first
    event caused by motion to the newest data in the ring when the first frame after it was sent (not the first
    deblurred frame; the heartbeat is off), i.e. the onset delay without the host's processing time.
    `clock_offset_us`: a fixed event clock offset (default: estimated), e.g. a real camera's few ms that each
    APS frame waits for its late events."""
    from edi_live.config import EdiConfig
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    events, frames, onset = noisy_scene(1.0 + 0.3, onset_s=1.0 + 0.01 * seed_shift)
    ring = ring if ring is not None else EventRing(capacity_events=1 << 22, capacity_frames=256, policy="wait")
    sent: list = []
    worker = EdiWorker(ring, default_reconstructor(240, 180, EdiConfig(clock_offset_us=clock_offset_us)),
                       EdiConfig(every=every, heartbeat_s=3600),
                       [lambda r: sent.append((r.t_us, ring.watermark_us))])
    worker.start()
    try:
        for p in scene_packets(events, frames):
            ring.push(p)
            if not ring.wait_consumer_idle(60):
                raise RuntimeError(f"the worker did not settle (error: {worker.error!r})")
    finally:
        ring.close()
        worker.done.wait(60)
    if worker.error is not None:
        raise RuntimeError(f"worker failed: {worker.error!r}")
    assert worker.events_in == len(events), "every event was read"
    early = [t for t, _ in sent[1:] if t < onset]
    assert not early, f"frames on the static part: {early}"
    later = [newest for t, newest in sent[1:] if t >= onset]
    return (later[0] - onset) if later else float("inf")
