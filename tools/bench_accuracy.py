"""Accuracy-versus-run-time benchmark of EDI and its baselines on simulated scenes with ground truth.

Owns the methods, the suite's run, its tables and plot (the scenes, metrics and shared harness are in
tools/accuracy_harness.py). For every scene (texture, speed, contrast thresholds incl. c_on != c_off, noise,
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
import inspect  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Callable  # noqa: E402

import numpy as np  # noqa: E402

from edi_live.simulation import SceneConfig, Simulation, preset, simulate, write_aedat4  # noqa: E402
from tools import baselines as bl  # noqa: E402
from tools.accuracy_harness import (Outputs, Score, _cpu, _edi_on, _events_between, _gt_targets,  # noqa: E402
                                    pitfall_suite, psnr, run_blurry, run_reconstructor, scene_suite, score, ssim)

REPO = Path(__file__).resolve().parent.parent


# --------------------------------------------------------------------------------------------- methods

def run_direct(sim: Simulation) -> Outputs:
    cfg = sim.config
    out = Outputs(note="true c")
    mids, lat = _gt_targets(sim)
    for k, f in enumerate(sim.frames):
        t0 = _cpu()
        out.deblurred[mids[k]] = (bl.blurry(f), (_cpu() - t0) * 1e3)
        for g in lat.get(k, []):
            t0 = _cpu()
            img = bl.direct_integration(f, sim.events, int(sim.gt_t_us[g]), cfg.c_on, cfg.c_off)
            out.latent[g] = (img, (_cpu() - t0) * 1e3)
    return out


def run_complementary(sim: Simulation, cutoff_hz: float = 0.5) -> Outputs:
    cfg = sim.config
    out = Outputs(note=f"true c, cutoff {cutoff_hz:g} Hz")
    cf = bl.ComplementaryFilter(cfg.width, cfg.height, cfg.c_on, cfg.c_off, cutoff_hz=cutoff_hz)
    ev = sim.events
    # timeline: every output time and every frame arrival (exposure end), in order
    todo = [(int(sim.gt_t_us[g]), 1, g) for g in range(sim.gt_t_us.size)]
    todo += [(f.exposure_end_us, 0, k) for k, f in enumerate(sim.frames)]
    todo.sort()
    last_t = int(ev["t"][0]) - 1 if ev.size else 0
    started = False
    for t, kind, i in todo:
        t0 = _cpu()
        cf.add_events(_events_between(ev, last_t, t)) if started else None
        last_t = t
        if kind == 0:
            cf.add_frame(sim.frames[i])
            started = True
            continue
        if not started:  # before the first frame the filter has nothing to show: use the first frame
            img = bl.blurry(sim.frames[0])
        else:
            img = cf.image_at(t)
        ms = (_cpu() - t0) * 1e3
        (out.deblurred if sim.gt_kind[i] == 0 else out.latent)[i] = (img, ms)
    return out


def run_edi_functions(sim: Simulation, c_on: float | None = None, c_off: float | None = None) -> Outputs:
    """EDI from edi_live.edi's pure functions with a given (default: the simulator's true) c."""
    from edi_live import edi

    cfg = sim.config
    c_on = cfg.c_on if c_on is None else c_on
    c_off = cfg.c_off if c_off is None else c_off
    frames = [edi.blurry_to_float(f.image) for f in sim.frames]
    return _edi_on(sim, sim.events, frames, c_on, c_off, Outputs(note=f"c_on={c_on:g} c_off={c_off:g}"))


def run_edi_estimator(sim: Simulation, make: Callable[[], object], *, c_start: float = 0.2,
                      event_map_tau: float = 0.5) -> Outputs:
    """EDI with c estimated afresh for every APS frame by an edi_live.contrast estimator (no caching).

    The ms per APS frame include everything: level table, event map / event counts the estimator needs,
    the c search and the deblur. Frame 0 has no predecessor: pair-based estimators start from c_start there.
    """
    from edi_live import contrast, edi

    cfg = sim.config
    est = make()
    out = Outputs()
    mids, lat = _gt_targets(sim)
    ev = sim.events
    prev = None
    c = (c_start, c_start)
    cs, evals = [], []
    for k, f in enumerate(sim.frames):
        t0 = _cpu()
        b, informative = edi.blurry_to_float(f.image)
        table = edi.build_level_table(ev, cfg.width, cfg.height, f.exposure_start_us, f.exposure_end_us,
                                      segments=True)
        emap = None
        if not getattr(est, "needs_pair", False):
            emap = contrast.event_map(ev, cfg.width, cfg.height, table.ref_t_us, f.exposure_start_us,
                                      f.exposure_end_us, event_map_tau * f.exposure_us)
        cur = contrast.FrameData(b, informative, table, emap)
        pair = None
        if prev is not None and getattr(est, "needs_pair", False):
            n_on, n_off = edi.signed_counts(ev, cfg.width, cfg.height, t0=prev.table.ref_t_us + 1, t1=table.ref_t_us)
            pair = contrast.FramePair(prev, cur, n_on, n_off)
        if "pairs" in inspect.signature(est.estimate).parameters:  # newer protocol: recent pairs, newest last
            got = est.estimate(cur, [pair] if pair is not None else [], c)
        else:
            got = est.estimate(cur, pair, c)
        if got is not None:
            c = (float(got[0]), float(got[1]))
        log_l = edi.deblur_log(b, table, c[0], c[1], informative=informative)
        img = np.exp(log_l)
        out.deblurred[mids[k]] = (img, (_cpu() - t0) * 1e3)
        cs.append(c)
        evals.append(getattr(est, "last_evaluations", 0))
        prev = cur
        state, t_state = log_l.copy(), table.ref_t_us
        for g in lat.get(k, []):
            t0 = _cpu()
            t = int(sim.gt_t_us[g])
            edi.propagate_log(state, _events_between(ev, t_state, t), c[0], c[1])
            t_state = t
            out.latent[g] = (np.exp(state), (_cpu() - t0) * 1e3)
    arr = np.array(cs[1:] or cs)
    out.note = f"c_on={np.median(arr[:, 0]):.3f} c_off={np.median(arr[:, 1]):.3f} (median)"
    if any(evals):
        out.note += f", {np.median(evals):.0f} evals"
    return out


def available_methods() -> list[tuple[str, Callable[[Simulation], Outputs], str]]:
    """(name, runner, group) for every method this checkout can run. group: 'baseline', 'oracle', 'auto'."""
    methods: list[tuple[str, Callable[[Simulation], Outputs], str]] = [
        ("blurry frame", run_blurry, "baseline"),
        ("direct integration", run_direct, "baseline"),
        ("complementary 0.5 Hz", run_complementary, "baseline"),
        ("complementary 5 Hz", lambda s: run_complementary(s, 5.0), "baseline"),
    ]
    try:
        import edi_live.edi  # noqa: F401
        methods.append(("EDI oracle c (edi.py)", run_edi_functions, "oracle"))
    except ImportError:
        pass
    try:
        from edi_live import contrast
    except ImportError:
        contrast = None
    if contrast is not None:
        for est in estimator_names():
            methods.append((f"EDI auto c: {est} (per frame)",
                            lambda s, e=est: run_edi_estimator(s, lambda: contrast.make_estimator(e)), "auto"))
            if "separate" in inspect.signature(contrast.ESTIMATORS[est]).parameters and est == "consistency":
                methods.append((f"EDI auto c: {est}, c_on/c_off (per frame)",
                                lambda s, e=est: run_edi_estimator(s, lambda: contrast.make_estimator(e, separate=True)),
                                "auto"))
    try:
        from edi_live.reconstructor import EdiReconstructor
    except ImportError:
        return methods
    methods.append(("EDI oracle c (reconstructor)",
                    lambda s: run_reconstructor(s, c_on=s.config.c_on, c_off=s.config.c_off), "oracle"))
    methods.append(("EDI default (reconstructor)", lambda s: run_reconstructor(s), "default"))
    del EdiReconstructor
    return methods


def estimator_names() -> list[str]:
    """c estimators that edi_live.contrast offers (its ESTIMATORS registry when present)."""
    try:
        from edi_live import contrast
    except ImportError:
        return []
    reg = getattr(contrast, "ESTIMATORS", None)
    if isinstance(reg, dict):
        return list(reg)
    if isinstance(reg, (list, tuple)):
        return list(reg)
    return []


# --------------------------------------------------------------------------------------------- scoring

def sweep_settings() -> list[tuple[str, str, Callable[[Simulation], Outputs]]]:
    """(curve, setting label, runner): c-search resolutions for the run-time/error trade-off curve."""
    try:
        from edi_live import contrast
    except ImportError:
        return []
    out = []
    if "consistency" in contrast.ESTIMATORS:
        for n_grid, tol, px in ((3, 5e-2, 250), (4, 2e-2, 500), (6, 1e-2, 1000), (8, 3e-3, 2000),
                                (10, 1e-3, 4000), (16, 1e-4, 16000)):
            mk = lambda n=n_grid, t=tol, m=px: contrast.make_estimator("consistency", n_grid=n, tol=t, max_pixels=m)
            out.append(("consistency: grid pts / tol / pixels", f"{n_grid}/{tol:g}/{px}",
                        lambda s, mk=mk: run_edi_estimator(s, mk)))
    try:
        import edi_live.reconstructor  # noqa: F401
        for k in (1, 2, 5, 0):
            out.append(("reconstructor default: re-estimate every K frames (0 = on fit-test failure)", f"K={k}",
                        lambda s, k=k: run_reconstructor(s, reestimate_every=k)))
    except ImportError:
        pass
    if "energy" in contrast.ESTIMATORS:
        for tol in (1e-1, 3e-2, 1e-2, 2e-3, 1e-4):
            mk = lambda t=tol: contrast.make_estimator("energy", tol=t)
            out.append(("energy: golden-section tol", f"{tol:g}", lambda s, mk=mk: run_edi_estimator(s, mk)))
    return out


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


# --------------------------------------------------------------------------------------------- reporting

def is_static(label: str) -> bool:
    return label.startswith("static")


def _agg(scores: list[Score]) -> tuple[float, float, float, float, float, float]:
    return (float(np.mean([r.psnr_deblur for r in scores])), float(np.mean([r.ssim_deblur for r in scores])),
            float(np.mean([r.psnr_latent for r in scores])), float(np.mean([r.ssim_latent for r in scores])),
            float(np.median([r.ms_deblur for r in scores])), float(np.median([r.ms_latent for r in scores])))


def per_scene_tables(results: dict[str, dict[str, Score]], methods) -> str:
    lines = []
    for label, per in results.items():
        lines.append(f"\n**{label}**\n")
        lines.append("| method | PSNR f (dB) | SSIM f | PSNR latent (dB) | SSIM latent | ms/APS frame | ms/latent frame | note |")
        lines.append("|---|---:|---:|---:|---:|---:|---:|---|")
        for n, _, _ in methods:
            if n in per:
                s = per[n]
                lines.append(f"| {n} | {s.psnr_deblur:.2f} | {s.ssim_deblur:.3f} | {s.psnr_latent:.2f} | "
                             f"{s.ssim_latent:.3f} | {s.ms_deblur:.2f} | {s.ms_latent:.2f} | {s.note} |")
    return "\n".join(lines)


def summary_table(results: dict[str, dict[str, Score]], methods) -> str:
    """Mean PSNR/SSIM over the moving scenes, median ms; one row per method."""
    moving = [lab for lab in results if not is_static(lab)]
    lines = [f"| method ({len(moving)} moving scenes) | PSNR f (dB) | SSIM f | PSNR latent (dB) | SSIM latent | "
             "ms/APS frame | ms/latent frame |", "|---|---:|---:|---:|---:|---:|---:|"]
    for n, _, _ in methods:
        rows = [results[lab][n] for lab in moving if n in results[lab]]
        if len(rows) != len(moving) or not rows:
            continue
        a = _agg(rows)
        lines.append(f"| {n} | {a[0]:.2f} | {a[1]:.3f} | {a[2]:.2f} | {a[3]:.3f} | {a[4]:.2f} | {a[5]:.2f} |")
    return "\n".join(lines)


def targets_report(results: dict[str, dict[str, Score]], methods) -> str:
    """Issue 2's accuracy targets: auto c within 0.3 dB of oracle c (mean over the whole suite, deblurred and
    latent); on the static scene never more than 0.5 dB below the blurry frame."""
    oracle = {"functions": "EDI oracle c (edi.py)", "reconstructor": "EDI oracle c (reconstructor)"}
    lines = ["| method | vs | dPSNR f, all scenes (dB) | dPSNR latent, all | dPSNR f, moving only | "
             "dPSNR latent, moving only | target: >= -0.3 dB | static: PSNR f - blurry | "
             "static: PSNR latent - blurry | target: >= -0.5 dB |",
             "|---|---|---:|---:|---:|---:|---|---:|---:|---|"]
    labels = list(results)
    static = [lab for lab in labels if is_static(lab)]
    for n, _, group in methods:
        if group not in ("auto", "default"):
            continue
        ref = oracle["reconstructor" if "reconstructor" in n else "functions"]
        pairs = [(results[lab][n], results[lab][ref]) for lab in labels if n in results[lab] and ref in results[lab]]
        if not pairs:
            continue
        dd = float(np.mean([a.psnr_deblur - b.psnr_deblur for a, b in pairs]))
        dl = float(np.mean([a.psnr_latent - b.psnr_latent for a, b in pairs]))
        mv = [(results[lab][n], results[lab][ref]) for lab in labels
              if not is_static(lab) and n in results[lab] and ref in results[lab]]
        md = float(np.mean([a.psnr_deblur - b.psnr_deblur for a, b in mv])) if mv else float("nan")
        ml = float(np.mean([a.psnr_latent - b.psnr_latent for a, b in mv])) if mv else float("nan")
        ok = "met" if min(dd, dl, md, ml) >= -0.3 else "MISSED"
        st = ["n/a", "n/a", "n/a"]
        for lab in static:
            per = results[lab]
            if n in per and "blurry frame" in per:
                sd = per[n].psnr_deblur - per["blurry frame"].psnr_deblur
                sl = per[n].psnr_latent - per["blurry frame"].psnr_latent
                st = [f"{sd:+.2f}", f"{sl:+.2f}", "met" if min(sd, sl) >= -0.5 else "MISSED"]
        lines.append(f"| {n} | {ref} | {dd:+.2f} | {dl:+.2f} | {md:+.2f} | {ml:+.2f} | {ok} | "
                     f"{st[0]} | {st[1]} | {st[2]} |")
    return "\n".join(lines)


def sweep_table(sweep_results) -> str:
    lines = ["| curve | setting | PSNR f (dB, moving) | PSNR latent (dB, moving) | median ms/APS frame | "
             "mean ms/APS frame | static PSNR f (dB) |", "|---|---|---:|---:|---:|---:|---:|"]
    for curve, settings in sweep_results.items():
        for setting, per in settings.items():
            mv = [sc for lab, sc in per.items() if not is_static(lab)]
            st = [sc.psnr_deblur for lab, sc in per.items() if is_static(lab)]
            if not mv:
                continue
            a = _agg(mv)
            mean_ms = float(np.mean([sc.ms_deblur_mean for sc in mv]))
            lines.append(f"| {curve} | {setting} | {a[0]:.2f} | {a[2]:.2f} | {a[4]:.2f} | {mean_ms:.2f} | "
                         f"{(f'{st[0]:.2f}' if st else 'n/a')} |")
    return "\n".join(lines)


def save_plot(path: str | Path, results: dict[str, dict[str, Score]], methods, sweep_results=None,
              title: str = "") -> None:
    """PSNR (mean over moving scenes) against ms per frame: a point per method, a line per c-search sweep.

    Panels: all methods at f; the EDI region at f, zoomed, with the sweeps; latent frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    moving = [lab for lab in results if not is_static(lab)]
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.8))
    markers = {"baseline": "s", "oracle": "*", "auto": "o", "default": "D"}
    edi_pts = []
    palette = plt.get_cmap("tab20").colors
    color = {name: palette[(2 * i) % 20 + (i // 10) % 2] for i, (name, _, _) in enumerate(methods)}
    for name, _, group in methods:
        rows = [results[lab][name] for lab in moving if name in results[lab]]
        if not rows:
            continue
        a = _agg(rows)
        kw = dict(marker=markers.get(group, "o"), s=120 if group == "oracle" else 50, label=name, zorder=3,
                  color=color[name])
        axes[0].scatter([max(a[4], 1e-3)], [a[0]], **kw)
        axes[2].scatter([max(a[5], 1e-3)], [a[2]], **kw)
        if group != "baseline":
            axes[1].scatter([max(a[4], 1e-3)], [a[0]], **kw)
            edi_pts.append(a[0])
    sweep_colors = ("black", "dimgray", "darkgoldenrod", "teal")
    for ci, (curve, settings) in enumerate((sweep_results or {}).items()):
        pts = []
        for setting, per in settings.items():
            mv = [sc for lab, sc in per.items() if not is_static(lab)]
            if mv:
                a = list(_agg(mv))
                a[4] = float(np.mean([sc.ms_deblur_mean for sc in mv]))  # amortised cost along a sweep
                pts.append((setting, a))
        pts.sort(key=lambda p: p[1][4])
        xs = [max(a[4], 1e-3) for _, a in pts]
        ys = [a[0] for _, a in pts]
        edi_pts += ys
        axes[1].plot(xs, ys, "--", lw=1, alpha=0.8, marker=".", color=sweep_colors[ci % len(sweep_colors)],
                     label=f"sweep {curve} (mean ms)")
        for j, ((setting, _), x, y) in enumerate(zip(pts, xs, ys)):
            axes[1].annotate(setting, (x, y), fontsize=6, rotation=30,
                             xytext=(2, 5 if j % 2 else -12), textcoords="offset points")
    if edi_pts:
        axes[1].set_ylim(min(edi_pts) - 0.4, max(edi_pts) + 0.4)
    titles = ("deblurred frame at f, all methods", "deblurred frame at f: EDI and its c-search settings",
              "latent frames between APS frames")
    xlabels = ("ms per APS frame, incl. c search (median, one core)",
               "ms per APS frame (points: median; sweeps: mean)", "ms per latent frame (median, one core)")
    for ax, what, xl in zip(axes, titles, xlabels):
        ax.set_xscale("log")
        ax.set_xlabel(xl, fontsize=8)
        ax.set_ylabel(f"mean PSNR (dB), {len(moving)} moving scenes", fontsize=8)
        ax.set_title(what, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    h0, l0 = axes[0].get_legend_handles_labels()
    h1, l1 = axes[1].get_legend_handles_labels()
    seen = set(l0)
    handles = h0 + [h for h, lab in zip(h1, l1) if lab not in seen]
    labels = l0 + [lab for lab in l1 if lab not in seen]
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=4, frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.13, 1, 0.97))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


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
