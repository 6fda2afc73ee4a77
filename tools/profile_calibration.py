"""Thread CPU of the per-APS-frame calibration parts over one replay, function by function.

The worker runs as tools/profile_node_cpu.py's `worker` mode runs it (ring filled beforehand, no publisher, the
APS deblur on the worker thread); the functions below are wrapped with a thread-CPU timer, which adds well under a
microsecond a call (no profiler: cProfile inflates the many small calls). Nested parts are counted in their callers
too. Run it from each checkout to compare two versions (alternate the runs: the machine is shared):

    python -m tools.profile_calibration RECORDING.aedat4 [--repeat 3]
"""

from __future__ import annotations

import argparse
import collections
import importlib
import time
from pathlib import Path

PARTS = [
    ("edi_live.frame_calibration", "FrameCalibration.before_deblur"),
    ("edi_live.frame_calibration", "FrameCalibration.settle"),
    ("edi_live.c_policy", "ContrastPolicy.update"),
    ("edi_live.contrast.consistency", "ConsistencyContrast.compare"),
    ("edi_live.contrast.consistency", "ConsistencyContrast._pair_problem"),
    ("edi_live.contrast.consistency", "ConsistencyContrast.estimate"),
    ("edi_live.black_level_policy", "BlackLevelPolicy.update"),
    ("edi_live.black_level_policy", "fit_black_level"),
    ("edi_live.black_level_policy", "samples_with_noise"),
    ("edi_live.clock_offset_policy", "ClockOffsetPolicy.update"),
    ("edi_live.clock_offset_policy", "ClockOffsetPolicy._fit"),
    ("edi_live.pixel_noise", "PixelNoise.update"),
    ("edi_live.pixel_noise", "PixelNoise._refresh"),
    ("edi_live.contrast_tracking", "ContrastTracker.step"),
    ("edi_live.contrast_tracking", "ContrastTracker.complete"),
    ("edi_live.pixel_masks", "UnreliablePixels.update"),
]


def _wrap(module: str, qualname: str, spent: dict, calls: collections.Counter) -> bool:
    owner = importlib.import_module(module)
    *path, name = qualname.split(".")
    for part in path:
        owner = getattr(owner, part, None)
    fn = getattr(owner, name, None)
    if fn is None:
        return False

    def timed(*args, **kwargs):
        t0 = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            spent[qualname] += time.thread_time() - t0
            calls[qualname] += 1
    setattr(owner, name, timed)
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.profile_calibration", description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--every", type=int, default=1000)
    args = ap.parse_args(argv)
    import drivers
    from edi_live.config import EdiConfig
    from edi_live.node import default_reconstructor
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    spent: dict[str, float] = collections.defaultdict(float)
    calls: collections.Counter = collections.Counter()
    missing = [q for m, q in PARTS if not _wrap(m, q, spent, calls)]
    cfg = EdiConfig(every=args.every, deblur_thread=False)
    worker_cpu = []
    for run in range(args.repeat + 1):  # the first run loads the kernels
        src = drivers.open_source("replay", path=args.recording, speed=0, loop=False)
        ring = EventRing(1 << 26, 1 << 14, "wait")
        with src:
            for packet in src:
                if packet is not None and not ring.push(packet, timeout_s=1.0):
                    raise SystemExit("the recording does not fit the ring (2**26 events, 2**14 frames)")
        ring.close()
        worker = EdiWorker(ring, default_reconstructor(src.info.width, src.info.height, cfg), cfg, [])
        if run == 1:
            spent.clear()
            calls.clear()
        c0 = time.thread_time()
        worker._run()
        if run:
            worker_cpu.append(time.thread_time() - c0)
    n = args.repeat
    print(f"{args.recording.name}: worker thread CPU s per run {[round(c, 3) for c in worker_cpu]}")
    print("| part | thread CPU ms per run | calls per run | ms per call |\n|---|---|---|---|")
    for name in sorted(spent, key=lambda k: -spent[k]):
        per_call = spent[name] / max(calls[name], 1) * 1e3
        print(f"| {name} | {spent[name] / n * 1e3:.1f} | {calls[name] // n} | {per_call:.3f} |")
    if missing:
        print(f"(not in this checkout: {', '.join(missing)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
