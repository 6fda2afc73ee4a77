"""Does thinning the settled calibration's checks (edi_live/calibration_schedule.py) cost accuracy? The realistic
benchmark's five mixed scenes, made long enough for the schedule to thin (its scenes are 10 frames: it never
does there), scored against ground truth with every check on every frame and with the default schedule.

    python -m tools.bench_schedule [--duration-s 3] [--every 4]

Per scene: PSNR at f / on latent frames of the node minus that of the oracle EDI that knows the camera
(tools/bench_realistic.py), for `settled_check_every` 1 and the given value, the fit tests left out and the
re-estimations of each run, and how many deblurred frames differ at all.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np

from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import simulate
from tools.accuracy_harness import run_reconstructor, score
from tools.bench_realistic import in_camera_tone, realistic_suite, run_oracle_camera, toned


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_schedule", description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration-s", type=float, default=3.0)
    ap.add_argument("--every", type=int, default=EdiReconstructor(8, 8).settings.settled_check_every)
    args = ap.parse_args(argv)
    if args.every < 2:
        ap.error("--every must be at least 2 (1 is the every-frame baseline it is compared with)")
    t_start = time.perf_counter()
    print(f"| scene | frames | every 1: node - oracle f / lat | every {args.every}: node - oracle f / lat | "
          f"difference f / lat | tests left out | re-estimations 1 / {args.every} | frames differing |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    gaps = {1: [], args.every: []}
    for group, label, cfg in realistic_suite():
        if group != "mix":
            continue
        sim = simulate(dataclasses.replace(cfg, duration_s=args.duration_s))
        truth = in_camera_tone(sim)
        gamma = float(sim.camera()["aps_gamma"])
        oracle = score(truth, toned(run_oracle_camera(sim), gamma))  # it writes linear light
        row, outs = {}, {}
        for every in (1, args.every):
            rec = EdiReconstructor(cfg.width, cfg.height, settled_check_every=every)
            outs[every] = out = run_reconstructor(sim, reconstructor=rec)
            s = score(truth, out)
            row[every] = (s.psnr_deblur - oracle.psnr_deblur, s.psnr_latent - oracle.psnr_latent,
                          rec._calib.tests_skipped, rec.reestimations)
            gaps[every].append(row[every][:2])
        differ = sum(not np.array_equal(outs[1].deblurred[g][0], outs[args.every].deblurred[g][0])
                     for g in outs[1].deblurred)
        a, b = row[1], row[args.every]
        print(f"| {label} | {len(sim.frames)} | {a[0]:+.2f} / {a[1]:+.2f} | {b[0]:+.2f} / {b[1]:+.2f} | "
              f"{b[0] - a[0]:+.2f} / {b[1] - a[1]:+.2f} | {b[2]} | {a[3]} / {b[3]} | {differ} |", flush=True)
    m1, mk = np.mean(gaps[1], axis=0), np.mean(gaps[args.every], axis=0)
    print(f"| **mean** | | {m1[0]:+.2f} / {m1[1]:+.2f} | {mk[0]:+.2f} / {mk[1]:+.2f} | "
          f"{mk[0] - m1[0]:+.2f} / {mk[1] - m1[1]:+.2f} | | | |")
    print(f"\nwall time {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
