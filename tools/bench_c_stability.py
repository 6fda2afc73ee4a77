"""How steady the estimated c is on the looped real recordings: re-estimations and the spread of c over time.

Each real DAVIS346 recording is replayed `--passes` times back to back (the replay's `--loop`: every pass moved
later by the recording's span) through the node's worker (replay policy, no deblur thread) in `--mode fused` with
the default reconstructor (c estimated, not given). After every APS frame c_on/c_off are read; reported per
recording and setting: re-estimations, how often c changed, and std/median of c_on and c_off over the frames from
the first estimate on (0 = c never moved; the same scene comes back every pass, so a steady estimator repeats
itself).

    python -m tools.bench_c_stability [--passes 3] [--joint-pairs 0,6]

`--joint-pairs K`: the policy pools the cost of the last K frame pairs (edi_live.contrast.joint) for its estimates
and fit tests; 0 = off (the single-pair policy, as in causal and nearest mode); `--mode fused` uses
edi_live.fused_mode.JOINT_PAIRS.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from drivers.replay import merged_packets
from edi_live.config import EdiConfig
from edi_live.datatypes import Packet
from edi_live.reconstructor import EdiReconstructor
from edi_live.ring import EventRing
from edi_live.worker import EdiWorker

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"


def looped_packets(path: Path, passes: int) -> list[Packet]:
    out: list[Packet] = []
    offset = 0
    for _ in range(passes):
        span: dict = {}
        out.extend(merged_packets(path, time_offset_us=offset, span=span))
        offset += span["t_last"] - span["t_first"] + 1
    return out


def c_series(path: Path, passes: int, joint_pairs: int, mode: str = "fused") -> dict:
    """Run the worker over the looped recording; c after every APS frame and the policy's counts."""
    packets = looped_packets(path, passes)
    first = next(f for p in packets for f in p.frames)
    h, w = first.image.shape[:2]
    rec = EdiReconstructor(w, h, **({"joint_pairs": joint_pairs} if joint_pairs else {}))
    seen: list[tuple[float, float, bool]] = []
    on_frame = rec.on_frame

    def recording_on_frame(frame, events, arrival_ns=0):
        out = on_frame(frame, events, arrival_ns)
        seen.append((rec.c_on, rec.c_off, rec.events_ignored))
        return out

    rec.on_frame = recording_on_frame  # type: ignore[method-assign]
    ring = EventRing(capacity_events=1 << 23, capacity_frames=256, policy="wait")
    errors: list = []
    worker = EdiWorker(ring, rec, EdiConfig(every=2000, mode=mode, deblur_thread=False, quality_every=0,
                                            heartbeat_s=1e6), [lambda r: None], on_error=errors.append)
    worker.start()
    for p in packets:
        ring.push(p, timeout_s=60)
    ring.close()
    worker.done.wait(600)
    if errors:
        raise errors[0]
    c = np.array([(a, b) for a, b, _ in seen], float)
    changes = int(np.count_nonzero(np.any(np.diff(c, axis=0) != 0, axis=1))) if len(c) > 1 else 0
    start = next((i for i, row in enumerate(c) if i and np.any(row != c[0])), 0)  # from the first estimate on
    steady = c[start:] if len(c) else c

    def spread(v: np.ndarray) -> float:
        return float(np.std(v) / np.median(v)) if v.size and np.median(v) > 0 else float("nan")

    return {"frames": len(c), "reestimations": rec.reestimations, "ill_conditioned": rec.ill_conditioned,
            "changes": changes, "spread_on": spread(steady[:, 0]), "spread_off": spread(steady[:, 1]),
            "c_median": tuple(float(np.median(steady[:, k])) for k in (0, 1)),
            "still_frames": sum(1 for *_, s in seen if s)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_c_stability", description=__doc__.split("\n\n")[0])
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--joint-pairs", default="0,6", help="comma-separated K values (0 = off)")
    ap.add_argument("--recordings", type=Path, nargs="*", default=sorted(REAL.glob("*.aedat4")))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    print("| recording | joint pairs K | APS frames | re-estimations | c changes | std/median c_on | "
          "std/median c_off | median c_on / c_off |")
    print("|---|---:|---:|---:|---:|---:|---:|---|")
    for path in args.recordings:
        for k in (int(v) for v in args.joint_pairs.split(",")):
            r = c_series(path, args.passes, k)
            print(f"| {path.stem} | {k or 'off'} | {r['frames']} | {r['reestimations']} | {r['changes']} | "
                  f"{r['spread_on']:.3f} | {r['spread_off']:.3f} | {r['c_median'][0]:.3f} / {r['c_median'][1]:.3f} |",
                  flush=True)
    print(f"\nwall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
