"""Where the node's CPU goes per emitted frame, and A/B ratios of node CPU time between two checkouts.

    python -m tools.profile_node_cpu profile [--input FILE] [--every 1000]   # cProfile of worker + publisher
    python -m tools.profile_node_cpu ab ../main [--input FILE] --repeat 5    # node CPU: this checkout vs another
    python -m tools.profile_node_cpu worker [../main] [--input FILE]        # worker-thread CPU: vs another
                                                                              # checkout, or calibration off vs on

`profile` runs the worker synchronously on one thread over a ring filled with the whole recording (decoded
beforehand, so the pump is not in it), every frame submitted to a real Publisher with one subscriber process
receiving everything, and groups cProfile's own-time per function into stages (EDI kernel, render, frame
bookkeeping, header packing, send, stats, deblur).

`worker` also reports, per APS frame, the thread CPU of the reconstructor's on_frame (the deblur, until the
deblurred frame is ready) and of settle() (the calibration checks deferred until it has left; none in checkouts
that predate it): the median frame of each run.

`ab` alternates this checkout and CHECKOUT in child processes (each imports its own edi_live), each child
running the full node (`tools.bench_stream.run_with_subscriber`: replay --speed 0 decoded in the child process
as the CLI does, one subscriber receiving every frame) and reporting node CPU seconds (the node process only).
On a shared machine only the ratios of one run mean anything: it prints, per input, the median and min/max of
new/old over the pairs.

This module owns the command line and the in-process modes (`profile`, `split`); the A/B modes' child processes
and tables are in tools/node_cpu_ab.py.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from pathlib import Path

import numpy as np

from tools.node_cpu_ab import ab, worker_ab

STAGES = (  # (stage, substrings of "file:function" that belong to it), first match wins
    ("quality score (edi_live/quality.py)", ("quality.py",)),
    ("deblur (APS frame, c estimation)", ("reconstructor.py:on_frame", "contrast", "c_policy", "deblur",
                                          "levels", "divisor", "finish_frame", "set_reference", "pixel_masks",
                                          "hot", "noise")),
    ("EDI kernel (propagate 1000 events, display refresh)", ("_kernels", "Propagator", "propagator", "apply")),
    ("render (copy of the display)", ("method 'copy'",)),
    ("header packing (dict + msgpack)", ("frame_header", "packb", "encode_frame", "header", "ascontiguous",
                                         "memoryview")),
    ("send (pyzmq / libzmq)", ("method 'send'", "socket.py", "_send_frame", "Frame")),
    ("stats (latency samples, counters)", ("add", "_Latency", "monotonic_ns", "take", "stats")),
    ("ring read", ("ring.py",)),
)


def _stage(key: tuple) -> str:
    file, _, func = key
    name = f"{Path(file).name}:{func}"
    for stage, needles in STAGES:
        if any(n in name for n in needles):
            return stage
    return "bookkeeping (worker, reconstruction, submit)"


def _filled_ring(path: Path):
    import drivers
    from edi_live.ring import EventRing

    src = drivers.open_source("replay", path=str(path), speed=0)
    ring = EventRing(1 << 24, 1 << 12, "wait")
    with src:
        for packet in src:
            if packet is not None:
                ring.push(packet)
    ring.close()
    return ring, src.info


def profile(path: Path, every: int, extra: dict, top: int) -> None:
    from edi_live.config import EdiConfig
    from edi_live.node import default_reconstructor
    from edi_live.publisher import Publisher
    from edi_live.worker import EdiWorker
    from tools.stream_harness import start_subscriber

    cfg = EdiConfig(every=every, deblur_thread=False, **extra)
    # warm the kernels on a first pass so that compile/load is not profiled
    ring, info = _filled_ring(path)
    EdiWorker(ring, default_reconstructor(info.width, info.height, cfg), cfg, [])._run()
    ring, info = _filled_ring(path)
    pub = Publisher(["tcp://127.0.0.1:*"], "profile", inbox_size=1 << 20, sndhwm=0, stats_interval_s=0.2)
    pub.start()
    proc, conn = start_subscriber(pub.bound_endpoints[0], 60)
    try:
        worker = EdiWorker(ring, default_reconstructor(info.width, info.height, cfg), cfg, [pub.submit])
        prof = cProfile.Profile()
        c0 = time.thread_time()
        prof.enable()
        worker._run()
        prof.disable()
        cpu_s = time.thread_time() - c0
        while pub.pending():
            time.sleep(0.01)
    finally:
        pub.close()
        conn.send("stop")
        sub = conn.recv() if conn.poll(30) else {}
        proc.join(10)
    if worker.error is not None:
        raise SystemExit(f"worker failed: {worker.error!r}")
    frames = sum(worker.sent.values())
    st = pstats.Stats(prof)
    by_stage: dict[str, float] = {}
    for key, (_, _, tottime, _, _) in st.stats.items():  # type: ignore[attr-defined]
        by_stage[_stage(key)] = by_stage.get(_stage(key), 0.0) + tottime
    total = sum(by_stage.values())
    print(f"\n## profile: {path.name} {info.width}x{info.height}, --every {every}, {worker.events_in} events, "
          f"{frames} frames sent ({worker.sent}), subscriber received {sub.get('frames')}")
    print(f"worker thread CPU {cpu_s:.3f} s under the profiler (which inflates small Python calls most: read the "
          f"shares, and `split` for costs without a profiler)")
    print("| stage | profiled s | share | µs per frame (profiled) |\n|---|---|---|---|")
    for stage, s in sorted(by_stage.items(), key=lambda kv: -kv[1]):
        print(f"| {stage} | {s:.3f} | {100 * s / total:.1f} % | {1e6 * s / max(1, frames):.1f} |")
    print(f"\ntop {top} functions by own time:")
    st.sort_stats("tottime").print_stats(top)


def _threads_cpu() -> dict[str, float]:
    """CPU seconds by thread name (comm) of this process, summed over threads of the same name (Linux)."""
    from tools.thread_cpu import thread_cpu_seconds

    out: dict[str, float] = {}
    for name, cpu_s in thread_cpu_seconds().values():
        out[name] = out.get(name, 0.0) + cpu_s
    return out


def split(path: Path, every: int, extra: dict, repeat: int) -> None:
    """Process CPU of the worker run synchronously (no pump) under configurations that add one part at a time,
    interleaved; differences per frame are each part's cost (no profiler overhead)."""
    from edi_live.config import EdiConfig
    from edi_live.node import default_reconstructor
    from edi_live.publisher import Publisher
    from edi_live.worker import EdiWorker
    from tools.stream_harness import start_subscriber

    configs = {"EDI only (no sink, no quality score)": (0, None), "+ quality score": (2, None),
               "+ publisher, nobody subscribed": (2, "idle"), "+ publisher, 1 subscriber (the node)": (2, "pub")}
    cpu: dict[str, list[float]] = {k: [] for k in configs}
    deblur: list[float] = []
    by_thread: dict[str, list[float]] = {}
    frames = events = 0
    pub = Publisher(["tcp://127.0.0.1:*"], "profile", inbox_size=1 << 20, sndhwm=0)
    idle = Publisher(["tcp://127.0.0.1:*"], "profile", inbox_size=1 << 20, sndhwm=0)
    pub.start()
    idle.start()
    proc, conn = start_subscriber(pub.bound_endpoints[0], 60)
    try:
        for r in range(repeat + 1):  # the first round warms kernels and caches; not counted
            for name, (quality, publish) in configs.items():
                cfg = EdiConfig(every=every, deblur_thread=False, quality_every=quality, **extra)
                ring, info = _filled_ring(path)
                sinks = {None: [], "idle": [idle.submit], "pub": [pub.submit]}[publish]
                worker = EdiWorker(ring, default_reconstructor(info.width, info.height, cfg), cfg, sinks)
                c0 = time.process_time()
                t0 = _threads_cpu()
                worker._run()
                while pub.pending() or idle.pending():
                    time.sleep(0.001)
                t1 = _threads_cpu()
                if r and publish == "pub":
                    for k, v in t1.items():
                        by_thread.setdefault(k, []).append(v - t0.get(k, 0.0))
                if r:
                    cpu[name].append(time.process_time() - c0)
                    deblur.append(sum(worker._deblur_ms) / 1e3)
                frames, events = sum(worker.sent.values()), worker.events_in
    finally:
        pub.close()
        idle.close()
        conn.send("stop")
        conn.recv() if conn.poll(30) else None
        proc.join(10)
    print(f"\n## split: {path.name} {info.width}x{info.height}, --every {every}, {events} events, {frames} frames, "
          f"{repeat} interleaved rounds; process CPU (worker run synchronously + publisher + libzmq threads)")
    print("| configuration | CPU s median (min-max) | µs per frame | added µs per frame | M events per CPU-s |")
    print("|---|---|---|---|---|")
    prev = None
    for name, values in cpu.items():
        med = float(np.median(values))
        added = "" if prev is None else f"{1e6 * (med - prev) / frames:.1f}"
        print(f"| {name} | {med:.3f} ({min(values):.3f}-{max(values):.3f}) | {1e6 * med / frames:.1f} | {added} | "
              f"{events / med / 1e6:.2f} |")
        prev = med
    print("threads with the publisher (median s, 10 ms ticks): " + ", ".join(
        f"{k} {np.median(v):.2f}" for k, v in sorted(by_thread.items(), key=lambda kv: -np.median(kv[1]))
        if np.median(v) > 0))
    d = float(np.median(deblur))
    print(f"of which APS deblur incl. c estimation (wall time, so inflated under load): {d:.3f} s = "
          f"{1e6 * d / frames:.1f} µs per frame")


CALIBRATION_OFF = {"flicker_mask": False, "noise_stats": False, "quality_every": 0, "black_level": 0.0,
                   "clock_offset_us": 0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.profile_node_cpu", description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=("profile", "split", "ab", "worker"))
    ap.add_argument("other", nargs="?", type=Path,
                    help="ab, worker: the other checkout (the old code); worker without it: calibration off vs on")
    ap.add_argument("--input", type=Path, action="append", help="recording(s) (default: simulated 240x180)")
    ap.add_argument("--every", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--c", type=float)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--nobody", action="store_true", help="ab: publish with nobody subscribed (node CPU incl. start-up)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="worker: these EdiConfig options against the default, or in both checkouts; ab: the new side's")
    args = ap.parse_args(argv)
    if not args.input:
        from tools.stream_harness import default_recording

        args.input = [default_recording()]
    from tools.bench_option import parse_setting

    if args.set and (args.mode not in ("worker", "ab") or args.nobody):
        ap.error("--set is for the worker mode, and for ab with a subscriber")
    if args.mode == "profile":
        for path in args.input:
            profile(path, args.every, {"c": args.c} if args.c else {}, args.top)
    elif args.mode == "worker":
        here = Path(__file__).resolve().parent.parent
        given = {"c": args.c} if args.c else {}
        chosen = dict(parse_setting(text) for text in args.set)
        given = {**given, **chosen} if args.other is not None else given
        runs = ({"old": (args.other.resolve(), given), "new": (here, given)} if args.other is not None else
                {"default": (here, given), " ".join(args.set): (here, {**given, **chosen})} if chosen else
                {"calibration off": (here, {**CALIBRATION_OFF, **given}), "calibration on": (here, given)})
        for path in args.input:
            worker_ab(runs, path.resolve(), args.every, args.repeat, args.passes)
    elif args.mode == "split":
        for path in args.input:
            split(path, args.every, {"c": args.c} if args.c else {}, args.repeat)
    else:
        if args.other is None:
            ap.error("ab needs the other checkout")
        ab(args.other.resolve(), args.input, args.every, args.repeat, args.passes, 0 if args.nobody else 1,
           dict(parse_setting(text) for text in args.set))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
