"""Where a still camera's CPU goes in the node: per thread, per function, and how often each part runs.

    python -m tools.profile_static_cpu [--seconds 10] [--cprofile] [--top 20] [--noise-hz 0.5] [--calls]

Runs the node as `bench_stream noise` does (a static 240x180 scene with background noise and APS frames at
20 fps, paced replay at speed 1 decoded in a child process, publisher with nobody subscribed) and, over
`--seconds` after a 2 s settling time, reports:
- CPU by thread from /proc (pump, edi-worker, publisher, main, libzmq's I/O thread), % of one core;
- counts per second: packets pumped, ring pushes, worker wake-ups and steps, chunks read, APS frames;
- with `--cprofile`, cProfile's own time per function for the worker and the pump thread (each profiled on its
  own thread, the whole run; the profiler inflates small Python calls, so read the shares and the call counts,
  and take the CPU figures from a run without it);
- with `--calls`, the worker thread's time per call of its main steps (thread time around each call, nested calls
  included in their callers; ~1 µs of wrapper per call): how often each runs and what one call costs in the node.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import threading
import time
from typing import Any, Callable

import numpy as np

_PROFILES: dict[str, cProfile.Profile] = {}


def _profiled(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def run(*args: Any, **kwargs: Any) -> Any:
        prof = _PROFILES.setdefault(name, cProfile.Profile())
        prof.enable()
        try:
            return fn(*args, **kwargs)
        finally:
            prof.disable()
    return run


class _Counted:
    """Counts calls of one method on a class, and the worker thread's calls and thread time in them (restored on
    exit)."""

    def __init__(self, cls: type, name: str) -> None:
        self.cls, self.name, self.calls = cls, name, 0
        self.worker_calls, self.worker_s = 0, 0.0
        self._orig = getattr(cls, name)

    def __enter__(self) -> "_Counted":
        orig = self._orig

        def counted(*args: Any, **kwargs: Any) -> Any:
            self.calls += 1
            if threading.current_thread().name != "edi-worker":
                return orig(*args, **kwargs)
            t0 = time.thread_time()
            try:
                return orig(*args, **kwargs)
            finally:
                self.worker_s += time.thread_time() - t0
                self.worker_calls += 1
        setattr(self.cls, self.name, counted)
        return self

    def __exit__(self, *exc: object) -> None:
        setattr(self.cls, self.name, self._orig)


def _step_counters() -> list[_Counted]:
    """The worker's main steps on a still scene, for --calls."""
    from edi_live.activity import StaticScene
    from edi_live.flicker_pixels import FlickerPixels
    from edi_live.latent_state import LatentState
    from edi_live.quality import PredictionScore
    from edi_live.quiet_reads import QuietReads
    from edi_live.reconstructor import EdiReconstructor
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    return [_Counted(EdiWorker, "_on_chunk"), _Counted(StaticScene, "segments"),
            _Counted(EdiReconstructor, "on_events"), _Counted(FlickerPixels, "steps"), _Counted(LatentState, "apply"),
            _Counted(PredictionScore, "on_events"), _Counted(EdiWorker, "_on_frame"),
            _Counted(PredictionScore, "on_aps_frame"), _Counted(EventRing, "window"), _Counted(QuietReads, "wake")]


def run(seconds: float, use_cprofile: bool, top: int, noise_hz: float, step_calls: bool = False) -> dict[str, Any]:
    from edi_live.config import NodeConfig
    from edi_live.deblur_handover import DeblurThread
    from edi_live.node import Node
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker
    from tools.stream_harness import replay_source
    from tools.stream_noise import noise_recording
    from tools.thread_cpu import ThreadCpu

    path = noise_recording(seconds + 4, noise_hz)
    saved = (EdiWorker._run, Node._pump_loop, DeblurThread._loop)
    if use_cprofile:
        EdiWorker._run = _profiled("edi-worker", EdiWorker._run)  # type: ignore[method-assign]
        Node._pump_loop = _profiled("pump", Node._pump_loop)  # type: ignore[method-assign]
        DeblurThread._loop = _profiled("edi-deblur", DeblurThread._loop)  # type: ignore[method-assign]
    counters = [_Counted(EventRing, "push"), _Counted(EventRing, "read_events"), _Counted(EdiWorker, "_step"),
                _Counted(EventRing, "wait")]
    steps = _step_counters() if step_calls else []
    try:
        for c in counters + steps:
            c.__enter__()
        cfg = NodeConfig.from_options({"replay": str(path), "publish": ["tcp://127.0.0.1:*"]})
        source = replay_source(path, 1.0)
        node = Node(cfg, source)
        thread = threading.Thread(target=node.run, daemon=True)
        thread.start()
        node.started.wait(60)
        time.sleep(2.0)
        calls0 = [c.calls for c in counters]
        timed0 = [(c.worker_calls, c.worker_s) for c in counters + steps]
        s0, cpu0, wall0 = node.stats(), time.process_time(), time.monotonic()
        with ThreadCpu() as threads:
            time.sleep(seconds)
        cpu, wall, s1 = time.process_time() - cpu0, time.monotonic() - wall0, node.stats()
        calls = {c.name: (c.calls - c0) / wall for c, c0 in zip(counters, calls0)}
        timed = [(f"{c.cls.__name__}.{c.name}", c.worker_calls - n0, c.worker_s - s0_)
                 for c, (n0, s0_) in zip(counters + steps, timed0)]
        node.stop()
        thread.join(30)
    finally:
        for c in reversed(counters + steps):
            c.__exit__()
        EdiWorker._run, Node._pump_loop, DeblurThread._loop = saved  # type: ignore[method-assign]
    d = {k: s1[k] - s0[k] for k in ("frames_out", "heartbeats", "aps_frames_in", "skipped_static_deblur",
                                     "events_processed")}
    by_thread = {k: 100 * v / wall for k, v in threads.cpu_s.items() if v > 0}
    print(f"\n## static 240x180 scene, {noise_hz} events/s per pixel of noise, APS 20 fps, paced replay, "
          f"{wall:.1f} s{' (under cProfile)' if use_cprofile else ''}")
    print(f"process CPU {100 * cpu / wall:.2f} % of one core; by thread (% of one core): " + ", ".join(
        f"{k} {v:.2f}" for k, v in sorted(by_thread.items(), key=lambda kv: -kv[1])))
    print(f"per second: events {d['events_processed'] / wall:.0f}, APS frames {d['aps_frames_in'] / wall:.1f}, "
          f"deblurs {(d['aps_frames_in'] - d['skipped_static_deblur']) / wall:.2f}, frames out "
          f"{d['frames_out'] / wall:.2f} (heartbeats {d['heartbeats'] / wall:.2f}), deblur p50 {s1.get('deblur_ms_p50')} ms "
          f"(wall), quiet waits {(s1.get('quiet_waits', 0) - s0.get('quiet_waits', 0)) / wall:.0f}; calls: " + ", ".join(
              f"{k} {v:.0f}" for k, v in calls.items()))
    if step_calls:
        print("\n| worker thread: call | calls/s | µs per call (thread time) | % of one core |\n|---|---|---|---|")
        for name, n, cpu_s in sorted(timed, key=lambda row: -row[2]):
            if n:
                print(f"| {name} | {n / wall:.1f} | {1e6 * cpu_s / n:.1f} | {100 * cpu_s / wall:.2f} |")
    for name, prof in _PROFILES.items():
        out = io.StringIO()
        pstats.Stats(prof, stream=out).sort_stats("tottime").print_stats(top)
        print(f"\n### cProfile, {name} thread (own time, whole run)\n" + out.getvalue())
    _PROFILES.clear()
    return {"process_pct": 100 * cpu / wall, "threads_pct": by_thread, "calls_per_s": calls}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.profile_static_cpu", description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--cprofile", action="store_true")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--noise-hz", type=float, default=0.5)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--calls", action="store_true", help="the worker thread's time per call of its main steps")
    args = ap.parse_args(argv)
    rows = [run(args.seconds, args.cprofile, args.top, args.noise_hz, args.calls) for _ in range(args.repeat)]
    if len(rows) > 1:
        p = np.array([r["process_pct"] for r in rows])
        print(f"\nprocess CPU over {len(rows)} runs: median {np.median(p):.2f} % ({p.min():.2f}-{p.max():.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
