"""Accuracy-versus-run-time benchmark of EDI and its baselines on simulated scenes with ground truth.

Owns the suite's run, the end-to-end run of the node and the command line; the methods are in
tools/accuracy_methods.py, the tables and plot in tools/accuracy_report.py, the scenes, metrics and shared harness
in tools/accuracy_harness.py. For every scene (texture, speed, contrast thresholds incl. c_on != c_off, noise,
hot pixels, one static scene) and every method it measures
(a) the deblurred frame at mid-exposure f and (b) the latent frames between APS frames against the
simulator's sharp ground truth, and the milliseconds each output costs (one core).

Methods: the blurry frame; direct integration from the blurry frame; the complementary filter
(Scheerlinck 2018); EDI with the true c (oracle); EDI with each c estimator of `edi_live.contrast`; and
the `EdiReconstructor` default. Prints a markdown table and saves a PSNR-versus-ms plot (the run-time/error
trade-off across c-search settings) to docs/bench_accuracy.png.

The realistic-camera section (`--realistic`) lives in tools/bench_realistic.py.

    python -m tools.bench_accuracy                       # full suite, a few minutes on one core
    python -m tools.bench_accuracy --quick               # 4 short scenes
    python -m tools.bench_accuracy --realistic [--quick] # the realistic-camera section
    python -m tools.bench_accuracy --modes [--realistic] [--quick]  # the node's causal/nearest/fused latent frames
                                                         # against the true-c oracles (tools/bench_modes.py)
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, as the targets say

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from edi_live.simulation import SceneConfig, preset, simulate, write_aedat4  # noqa: E402
from tools.accuracy_harness import Score, pitfall_suite, psnr, scene_suite, score, ssim  # noqa: E402
from tools.accuracy_methods import available_methods, sweep_settings  # noqa: E402
from tools.accuracy_report import (per_scene_tables, save_plot, summary_table, sweep_table,  # noqa: E402
                                   targets_report)

REPO = Path(__file__).resolve().parent.parent


def run_suite(scenes, methods, sweeps=(), *, log=print):
    """Simulate each scene once; score every method and every sweep setting on it.

    Returns (results[scene][method] -> Score, sweep_results[curve][setting][scene] -> Score).
    """
    results: dict[str, dict[str, Score]] = {}
    sweep_results: dict[str, dict[str, dict[str, Score]]] = {}
    for label, cfg in scenes:
        t0 = time.perf_counter()
        sim = simulate(cfg)
        log(f"# {label}: {sim.events.size} events ({int(sim.is_noise.sum())} noise), {len(sim.frames)} APS frames, "
            f"simulated in {sim.wall_s:.1f} s")
        results[label] = {}
        for name, runner, _ in methods:
            try:
                results[label][name] = score(sim, runner(sim))
            except Exception as exc:  # a method that fails is reported, not fatal to the benchmark
                log(f"  {name}: FAILED {type(exc).__name__}: {exc}")
        for curve, setting, runner in sweeps:
            try:
                sweep_results.setdefault(curve, {}).setdefault(setting, {})[label] = score(sim, runner(sim))
            except Exception as exc:
                log(f"  sweep {curve} {setting}: FAILED {type(exc).__name__}: {exc}")
        log(f"  scored in {time.perf_counter() - t0:.1f} s")
    return results, sweep_results


def node_end_to_end(cfg: SceneConfig, workdir: Path, *, every: int = 2000, log=print) -> str:
    """The whole pipeline on a simulated recording: simulate -> .aedat4 -> `edi-live --replay --speed 0 --out`
    -> read the emitted frames back -> PSNR/SSIM against ground truth rendered at the emitted times."""
    import subprocess

    from edi_live.aedat4.reader import Aedat4Reader

    workdir.mkdir(parents=True, exist_ok=True)
    rec, out = workdir / "e2e_in.aedat4", workdir / "e2e_out.aedat4"
    sim = simulate(dataclasses.replace(cfg, ground_truth=False))
    write_aedat4(sim, rec)
    cmd = [sys.executable, "-m", "edi_live", "--replay", str(rec), "--speed", "0", "--no-publish", "--out", str(out),
           "--every", str(every)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return f"node run failed (exit {proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}"
    frames = []
    with Aedat4Reader(out) as reader:
        for info, item in reader:
            if info.type == "FRME":
                frames.append(item)
    mids = set(int(m) for m in sim.mid_exposure_us)
    rel = sorted({f.exposure_start_us - cfg.t0_us for f in frames})
    truth = simulate(dataclasses.replace(cfg, latent_per_interval=0, gt_extra_us=tuple(rel)))
    first_mid = int(sorted(mids)[1])  # skip the first APS frame (warm-up), as the suite does
    rows: dict[str, list] = {"deblurred": [], "latent": [], "APS frame at the deblurred times": [],
                             "newest APS frame at the latent times": []}
    ends = np.array([f.exposure_end_us for f in sim.frames])
    for f in frames:
        t = f.exposure_start_us
        if t < first_mid:
            continue
        gi = int(np.flatnonzero(truth.gt_t_us == t)[0])
        gt = truth.gt_images[gi]
        kind = "deblurred" if t in mids else "latent"
        rows[kind].append((psnr(f.image, gt), ssim(f.image, gt)))
        if kind == "deblurred":
            aps = sim.frames[int(np.flatnonzero(sim.mid_exposure_us == t)[0])].image
            rows["APS frame at the deblurred times"].append((psnr(aps, gt), ssim(aps, gt)))
        else:  # what a plain APS viewer shows at t: the newest frame whose exposure has ended
            k = int(np.searchsorted(ends, t, side="right")) - 1
            if k >= 0:
                aps = sim.frames[k].image
                rows["newest APS frame at the latent times"].append((psnr(aps, gt), ssim(aps, gt)))
    shown = ["edi-live"] + [Path(c).name if c.startswith(str(workdir)) else c for c in cmd[3:]]
    lines = [f"`{' '.join(shown)}` on a {cfg.width}x{cfg.height} simulated recording "
             f"({sim.events.size} events, {len(sim.frames)} APS frames): {len(frames)} frames out in {wall:.1f} s wall",
             "", "| node output | frames | mean PSNR (dB) | mean SSIM |", "|---|---:|---:|---:|"]
    for kind, vals in rows.items():
        if vals:
            lines.append(f"| {kind} | {len(vals)} | {np.mean([v[0] for v in vals]):.2f} | "
                         f"{np.mean([v[1] for v in vals]):.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_accuracy", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="4 short scenes instead of 8, no sweep")
    ap.add_argument("--no-sweep", action="store_true", help="skip the c-search resolution sweep")
    ap.add_argument("--pitfalls", action="store_true",
                    help="also run scenes with APS offset/gamma and late events (not in the means or targets)")
    ap.add_argument("--plot", default=str(REPO / "docs" / "bench_accuracy.png"), help="PNG path ('' = none)")
    ap.add_argument("--no-node", action="store_true", help="skip the end-to-end run of edi-live on the demo recording")
    ap.add_argument("--realistic", action="store_true",
                    help="only the realistic-camera section: blurry frame, default node and an EDI that knows the "
                         "true camera, on scenes with mixes of camera effects and each effect alone")
    ap.add_argument("--linear", action="store_true",
                    help="with --realistic: score in linear light instead of the camera's tone (tools/bench_realistic.py)")
    ap.add_argument("--modes", action="store_true",
                    help="only the modes section: the node's causal, nearest and fused latent frames against EDI "
                         "with the true c from each reference rule (tools/bench_modes.py)")
    args = ap.parse_args(argv)
    if args.modes:
        from tools import bench_modes

        return bench_modes.main((["--quick"] if args.quick else []) + (["--realistic"] if args.realistic else []))
    if args.realistic:
        from tools import bench_realistic

        return bench_realistic.main((["--quick"] if args.quick else []) + (["--linear"] if args.linear else []))
    methods = available_methods()
    scenes = scene_suite(args.quick)
    sweeps = [] if (args.quick or args.no_sweep) else sweep_settings()
    t0 = time.perf_counter()
    results, sweep_results = run_suite(scenes, methods, sweeps)
    print("\n## Mean over the moving scenes\n")
    print(summary_table(results, methods))
    print("\n## Targets (mean over all scenes; static scene against the blurry frame)\n")
    print(targets_report(results, methods))
    if sweep_results:
        print("\n## c-search resolution sweep (per-frame estimation)\n")
        print(sweep_table(sweep_results))
    if not (args.quick or args.no_node):
        import tempfile

        print("\n## End to end: the node on the demo recording\n")
        with tempfile.TemporaryDirectory() as tmp:
            try:
                print(node_end_to_end(preset("demo"), Path(tmp)))
            except Exception as exc:  # the node is another team's code: report, do not abort the benchmark
                print(f"end-to-end run failed: {type(exc).__name__}: {exc}")
    print("\n## Per scene\n")
    print(per_scene_tables(results, methods))
    if args.pitfalls:
        print("\n## Pitfall scenes (not in the means above)\n")
        pit, _ = run_suite(pitfall_suite(), methods)
        print(per_scene_tables(pit, methods))
    if args.plot:
        save_plot(args.plot, results, methods, sweep_results,
                  title=f"python -m tools.bench_accuracy{' --quick' if args.quick else ''}: {len(scenes)} scenes")
        print(f"\nplot: {args.plot}")
    print(f"\nwall time {time.perf_counter() - t0:.0f} s (numba kernels: "
          f"{'on' if _have_numba() else 'off'})")
    return 0


def _have_numba() -> bool:
    try:
        from edi_live import edi
        return edi.have_numba()
    except ImportError:
        return False


if __name__ == "__main__":
    sys.exit(main())
