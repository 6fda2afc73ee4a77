"""Fits the residual tables of edi_live.edi.residual (TABLE_A, TABLE_B) on the simulator's ground truth.

The simulator knows each pixel's true crossing level S(t) (its start level plus its own thresholds over the
signal events), so the residual the step model leaves is r(t) = log I(t) - S(t), in (-c_off, c_on). At every
ground-truth time of the ideal benchmark scenes (tools/bench_accuracy.scene_suite, moving scenes, first 0.2 s)
and for every pixel with a last event (at t_a, sign s_a) and a next one (t_b, s_b), r / c is regressed on
(s_a, s_b) in NBINS bins of x = (t - t_a) / (t_b - t_a): r = A(x) s_a c + B(x) s_b c. Prints the tables, the
rms of r / c before and after (all pixels with both events), and the same with each scene left out of the fit.

    python -m tools.fit_residual [--duration 0.2] [--bins 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np


def residual_samples(cfg, duration_s: float) -> np.ndarray:
    """Rows (r / c, s_a, s_b, x) for every pixel with a last and a next signal event at each ground-truth time."""
    from edi_live.simulation import simulate
    from edi_live.simulation.motion import Renderer

    cfg = dataclasses.replace(cfg, duration_s=duration_s)
    sim = simulate(cfg)
    w, h = cfg.width, cfg.height
    ev = sim.events[~sim.is_noise]
    pix = ev["y"].astype(np.int64) * w + ev["x"]
    con, coff = sim.c_on_map.reshape(-1).astype(np.float64), sim.c_off_map.reshape(-1).astype(np.float64)
    step = np.where(ev["p"], con[pix], -coff[pix])
    t_rel = ev["t"] - ev["t"].min()
    order = np.lexsort((t_rel, pix))  # by pixel, then time
    key = pix[order] * (1 << 42) + t_rel[order]
    start = Renderer(cfg).log_frame(0.0).astype(np.float64).reshape(-1) + np.log(255.0)
    rows = []
    everyone = np.arange(w * h, dtype=np.int64)
    for g in range(3, len(sim.gt_t_us)):
        t = int(sim.gt_t_us[g]) - int(ev["t"].min())
        upto = t_rel <= t
        level = start + np.bincount(pix[upto], weights=step[upto], minlength=w * h)
        r = np.log(sim.gt_images[g].astype(np.float64)).reshape(-1) - level
        nxt = np.searchsorted(key, everyone * (1 << 42) + t, side="right")
        a, b = nxt - 1, np.minimum(nxt, key.size - 1)
        ok = (a >= 0) & (nxt < key.size)
        ok[ok] &= (pix[order[a[ok]]] == everyone[ok]) & (pix[order[b[ok]]] == everyone[ok])
        ea, eb = order[a[ok]], order[b[ok]]
        c = np.where(ev["p"][eb], con[ok], coff[ok])
        x = (t - t_rel[ea]) / np.maximum(t_rel[eb] - t_rel[ea], 1)
        rows.append(np.stack([r[ok] / c, np.where(ev["p"][ea], 1.0, -1.0), np.where(ev["p"][eb], 1.0, -1.0), x], 1))
    return np.concatenate(rows)


def fit(rows: np.ndarray, bins: int) -> np.ndarray:
    """(bins, 2) least-squares (A, B) per bin of x."""
    i = np.minimum((rows[:, 3] * bins).astype(int), bins - 1)
    return np.array([np.linalg.lstsq(rows[i == j][:, 1:3], rows[i == j][:, 0], rcond=None)[0] for j in range(bins)])


def rms_after(rows: np.ndarray, table: np.ndarray) -> float:
    i = np.minimum((rows[:, 3] * len(table)).astype(int), len(table) - 1)
    est = table[i, 0] * rows[:, 1] + table[i, 1] * rows[:, 2]
    return float(np.sqrt(np.mean((rows[:, 0] - est) ** 2)))


def main(argv: list[str] | None = None) -> int:
    from tools.accuracy_harness import scene_suite

    ap = argparse.ArgumentParser(prog="python -m tools.fit_residual", description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=0.2)
    ap.add_argument("--bins", type=int, default=10)
    args = ap.parse_args(argv)
    per_scene = {label: residual_samples(cfg, args.duration) for label, cfg in scene_suite(False)
                 if not label.startswith("static")}
    rows = np.concatenate(list(per_scene.values()))
    table = fit(rows, args.bins)
    print("TABLE_A =", np.array2string(table[:, 0], precision=3, separator=", "))
    print("TABLE_B =", np.array2string(table[:, 1], precision=3, separator=", "))
    print(f"rms r/c: step {np.sqrt(np.mean(rows[:, 0] ** 2)):.3f}, estimate {rms_after(rows, table):.3f} "
          f"({len(rows)} pixel-times with a last and a next event)")
    for label, held in per_scene.items():
        rest = np.concatenate([v for k, v in per_scene.items() if k != label])
        print(f"  {label} left out: step {np.sqrt(np.mean(held[:, 0] ** 2)):.3f}, "
              f"estimate {rms_after(held, fit(rest, args.bins)):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
