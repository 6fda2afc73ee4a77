"""End-to-end streaming benchmarks of the edi-live node (numbers, not pass/fail).

    python -m tools.bench_stream throughput   # replay --speed 0 -> worker -> publish -> 1 subscriber, --every 1000
    python -m tools.bench_stream stages       # CPU per stage, each alone on one thread (per frame / per event)
    python -m tools.bench_stream latency      # paced replay at ~1 M events/s: latency p50/p99, arrival -> sent
    python -m tools.bench_stream memory       # PSS over a looped replay (--seconds 60; 600 for the 10-minute run)
    python -m tools.bench_stream static       # CPU of the node on a static scene (APS frames, no events)
    python -m tools.bench_stream noise        # static scene with sensor noise: CPU, frames out, motion-onset delay
    python -m tools.bench_stream noise --against ../main   # the same, A/B against another checkout
    python -m tools.bench_stream scaling      # worker cost per latent frame vs changed pixels and resolution
    python -m tools.bench_stream all

Input: `--input FILE.aedat4`, or by default a 240x180 recording simulated once by tools/simulate.py (preset
"fast") and cached in the temp directory. The subscriber runs in its own process, as a viewer would.
Figures are medians of `--repeat` runs where it makes sense; each mode prints what limits it.

This module owns the command line; the modes are in tools/stream_throughput.py (throughput, stages, scaling),
tools/stream_latency.py, tools/stream_memory.py, tools/stream_static.py and tools/stream_noise.py, the node run
they share in tools/stream_harness.py.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

# run_with_subscriber stays importable from here: `profile_node_cpu ab` runs its child script in both checkouts, and
# an older one has no tools/stream_harness.py
from tools.stream_harness import default_recording, run_with_subscriber  # noqa: F401
from tools.stream_latency import bench_latency
from tools.stream_memory import bench_memory
from tools.stream_noise import bench_noise, bench_noise_ab
from tools.stream_static import bench_static
from tools.stream_throughput import bench_scaling, bench_stages, bench_throughput


def _extra(args: argparse.Namespace) -> dict:
    extra: dict = {}
    if args.c is not None:
        extra["c"] = args.c
    if args.no_deblur_thread:
        extra["deblur_thread"] = False
    if args.no_deblur_ahead:
        extra["deblur_ahead"] = False
    if args.clock_offset_us is not None:
        extra["clock_offset_us"] = args.clock_offset_us
    return extra


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_stream", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("throughput", "stages", "latency", "memory", "static", "noise", "scaling",
                                     "all"))
    ap.add_argument("--input", type=Path, help="an .aedat4 recording (default: simulated 240x180, cached)")
    ap.add_argument("--every", type=int, default=1000, help="events per latent frame (default 1000)")
    ap.add_argument("--repeat", type=int, default=3, help="runs for medians (default 3)")
    ap.add_argument("--passes", type=int, default=5, help="throughput: passes over the recording (default 5)")
    ap.add_argument("--rate", type=float, default=1e6, help="latency mode: paced event rate, events/s (default 1e6)")
    ap.add_argument("--seconds", type=float, default=None,
                    help="memory: run length (default 60; use 600 for the 10-minute run); latency/static: 10")
    ap.add_argument("--c", type=float, help="throughput/latency: fixed contrast threshold (default: estimated)")
    ap.add_argument("--no-deblur-ahead", action="store_true",
                    help="throughput/latency: read each exposure's events at its end (the node's deblur-ahead = false)")
    ap.add_argument("--clock-offset-us", type=int, default=None,
                    help="throughput/latency: give the event clock offset instead of estimating it")
    ap.add_argument("--no-deblur-thread", action="store_true",
                    help="throughput/latency: deblur APS frames on the worker thread (the node's deblur-thread = false)")
    ap.add_argument("--speed", type=float, default=1.0, help="memory mode: replay speed (default 1 = real time)")
    ap.add_argument("--against", type=Path, default=None,
                    help="noise mode: A/B against another checkout (e.g. ../main), each run in its own process")
    args = ap.parse_args(argv)
    path = args.input
    if args.mode in ("throughput", "stages", "latency", "memory", "all") and path is None:
        path = default_recording()
    print(f"machine: {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, numpy {np.__version__}")
    if args.mode in ("throughput", "all"):
        bench_throughput(path, args.every, args.repeat, args.passes, extra=_extra(args))
    if args.mode in ("stages", "all"):
        bench_stages(path, args.every, args.repeat, extra={"c": args.c} if args.c is not None else None)
    if args.mode in ("latency", "all"):
        bench_latency(path, args.every, args.rate, args.seconds or 10.0, extra=_extra(args))
    if args.mode in ("static", "all"):
        bench_static(args.seconds or 10.0)
    if args.mode in ("noise", "all") and args.against is not None:
        bench_noise_ab(args.seconds or 20.0, args.repeat, args.against.resolve())
    elif args.mode in ("noise", "all"):
        bench_noise(args.seconds or 20.0, args.repeat)
    if args.mode in ("scaling", "all"):
        bench_scaling(args.every, args.repeat)
    if args.mode in ("memory", "all"):
        bench_memory(path, args.every, args.seconds or 60.0, args.speed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
