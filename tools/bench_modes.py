"""Latent-frame modes of the node (causal / nearest / fused) against EDI with the true c, on simulated scenes.

Owns the modes section of the accuracy benchmark (`python -m tools.bench_accuracy --modes`). For each scene the
real worker (edi_live.worker.EdiWorker, replay policy, no deblur thread) runs with an EdiReconstructor that is
given the true c_on/c_off, in each mode; every emitted latent frame is then scored against

- the ground truth at its own time (the scene is simulated again with those times as extra ground-truth times),
- the oracles: EDI from edi_live.edi's public functions with the true c, from the newest APS frame whose
  exposure has ended (causal rule), the previous mid-exposure, and the nearest mid-exposure,
- and, per frame, the oracle with the node's own reference (`ref_t_us`), which isolates hand-over losses.

Temporal consistency: the mean absolute frame-to-frame change (8-bit) between consecutive emitted latent frames,
at the frame pairs whose reference differs (causal: a new APS frame arrived; nearest: the midpoint between
frames; fused: a new pair of frames at each mid-exposure) divided by the same figure elsewhere, each normalised by the ground truth's own change
between the same two times. 1 = no jump.

    python -m tools.bench_modes [--quick] [--realistic]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from dataclasses import dataclass

import numpy as np

from edi_live.simulation import Simulation, simulate

MODES_RUN = ("causal", "nearest", "fused", "fused+residual")  # fused+residual: --mode fused --fused-residual


@dataclass
class ModeRun:
    times: np.ndarray  # latent frame times (µs)
    refs: np.ndarray  # their ref_t_us
    images: list[np.ndarray]  # uint8
    waited_ms: float | None
    wall_ms_per_latent: float
    cpu_ms_per_latent: float  # the worker thread's CPU time (deblurs included) per latent frame


def feed_worker(sim: Simulation, mode: str, every: int, c: tuple[float, float] | None,
                joint_pairs: int = 0) -> ModeRun:
    """The node's worker on the simulated stream (APS frames in the packet holding their exposure end); c None:
    estimated by the reconstructor (with joint c over `joint_pairs` pairs if > 0)."""
    from edi_live.config import EdiConfig
    from edi_live.datatypes import Packet
    from edi_live.reconstructor import EdiReconstructor
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    cfg = sim.config
    mode, residual = mode.split("+")[0], mode.endswith("+residual")
    ring = EventRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    # "fused" is --no-fused-residual, "fused+residual" the node's fused default; the flicker mask as the node sets it
    settings = {"fused_residual": residual, "mask_flicker_pixels": mode != "fused"}
    rec = (EdiReconstructor(cfg.width, cfg.height, c_on=c[0], c_off=c[1], **settings) if c is not None
           else EdiReconstructor(cfg.width, cfg.height, joint_pairs=joint_pairs, **settings))
    out: list = []
    errors: list = []
    worker = EdiWorker(ring, rec, EdiConfig(every=every, mode=mode, deblur_thread=False, quality_every=0,
                                            heartbeat_s=1e6), [out.append], on_error=errors.append)
    ev = sim.events
    cut = 0
    t0 = time.perf_counter()
    worker.start()
    for f in sim.frames:
        end = int(np.searchsorted(ev["t"], f.exposure_end_us, side="right"))
        ring.push(Packet(events=ev[cut:end], frames=[f]), timeout_s=60)
        cut = end
    ring.push(Packet(events=ev[cut:]), timeout_s=60)
    ring.close()
    worker.done.wait(600)
    wall = time.perf_counter() - t0
    if errors:
        raise errors[0]
    lat = [r for r in out if r.kind == "latent"]
    return ModeRun(np.array([r.t_us for r in lat], np.int64), np.array([r.ref_t_us for r in lat], np.int64),
                   [r.image for r in lat], worker.stats()[f"{mode}_added_latency_ms_p50"] if mode != "causal" else None,
                   wall * 1e3 / max(1, len(lat)), worker.cpu_s * 1e3 / max(1, len(lat)))


class Oracle:
    """EDI with given c from edi_live.edi's public functions: log L_k(f_k) per APS frame, and log L(t) from any
    reference frame by the events between (forward or backward)."""

    def __init__(self, sim: Simulation, c: tuple[float, float]) -> None:
        from edi_live import edi

        cfg = sim.config
        self.sim, self.c = sim, c
        self.mids = sim.mid_exposure_us
        self.ends = np.array([f.exposure_end_us for f in sim.frames], np.int64)
        self.log_ref = []
        for f in sim.frames:
            b, informative = edi.blurry_to_float(f.image)
            table = edi.build_level_table(sim.events, cfg.width, cfg.height, f.exposure_start_us, f.exposure_end_us,
                                          segments=c[0] != c[1])
            self.log_ref.append(edi.deblur_log(b, table, c[0], c[1], informative=informative))

    def log_at(self, t: int, k: int) -> np.ndarray:
        from edi_live import edi

        cfg, f = self.sim.config, int(self.mids[k])
        lo, hi = (f, t) if t >= f else (t, f)
        d = edi.event_delta(self.sim.events, cfg.width, cfg.height, *self.c, t0=lo + 1, t1=hi)
        return np.clip(self.log_ref[k] + (d if t >= f else -d), edi.LOG_MIN, edi.LOG_MAX)

    def image(self, t: int, k: int) -> np.ndarray:
        from edi_live import edi

        return edi.to_uint8(self.log_at(t, k).astype(np.float32))

    def causal(self, t: int) -> int:
        """The newest APS frame whose exposure has ended by t (what a causal node can use)."""
        return max(0, int(np.searchsorted(self.ends, t, side="right")) - 1)

    def previous(self, t: int) -> int:
        return max(0, int(np.searchsorted(self.mids, t, side="right")) - 1)

    def nearest(self, t: int) -> int:
        k = self.previous(t)
        if k + 1 < len(self.mids) and self.mids[k + 1] - t < t - self.mids[k]:
            return k + 1
        return k


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    from tools.accuracy_harness import psnr as _psnr

    return _psnr(a, b)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    from tools.accuracy_harness import ssim as _ssim

    return _ssim(a, b)


def consistency(times: np.ndarray, images: list[np.ndarray], gt: list[np.ndarray], switch: np.ndarray) -> float:
    """Frame-to-frame change at reference switches over the change elsewhere, each relative to the ground truth's
    change between the same times (mean |Δ| output / mean |Δ| truth). switch[i]: a switch between i and i+1."""
    at, away = [], []
    for i in range(len(times) - 1):
        d_out = float(np.mean(np.abs(images[i + 1].astype(np.float64) - images[i])))
        d_gt = float(np.mean(np.abs(np.clip(gt[i + 1], 0, 255) - np.clip(gt[i], 0, 255))))
        if d_gt <= 1e-6:
            continue
        (at if switch[i] else away).append(d_out / d_gt)
    if not at or not away:
        return float("nan")
    return float(np.mean(at) / np.mean(away))


def reference_index(mids: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """Index of the APS frame each latent frame's ref_t_us names. ref_t_us is that frame's mid-exposure in the event
    clock, so once the node has estimated a clock offset (it does whenever c is estimated) it sits that offset
    away from the simulator's mid-exposure: the nearest mid-exposure is the frame (offsets are a few ms, frames
    tens of ms apart)."""
    mids = np.asarray(mids, np.int64)
    refs = np.asarray(refs, np.int64)
    k = np.clip(np.searchsorted(mids, refs), 1, max(1, len(mids) - 1))
    before = np.clip(k - 1, 0, len(mids) - 1)
    after = np.clip(k, 0, len(mids) - 1)
    return np.where(np.abs(refs - mids[before]) <= np.abs(mids[after] - refs), before, after)


def score_scene(label: str, sim: Simulation, *, every: int, modes=MODES_RUN, c: tuple[float, float] | None = None,
                log=print, estimate_c: tuple[int, ...] = ()) -> dict[str, dict[str, float]]:
    """Per mode: PSNR/SSIM against the truth, PSNR against the oracles, consistency, latency and cost. With
    `estimate_c` (joint-pair counts K, 0 = off) each mode also runs with c estimated, as "MODE, c est. K"."""
    cfg = sim.config
    c = (float(cfg.c_on), float(cfg.c_off)) if c is None else c
    runs = {m: feed_worker(sim, m, every, c) for m in modes}
    runs.update({f"{m}, c est. K={k}": feed_worker(sim, m, every, None, k) for m in modes for k in estimate_c})
    skip = int(sim.mid_exposure_us[1])  # the first interval warms up the state (as the accuracy suite skips it)
    last = int(sim.mid_exposure_us[-1])
    times = sorted({int(t) for r in runs.values() for t in r.times if skip <= t < last})
    truth = simulate(dataclasses.replace(cfg, latent_per_interval=0, gt_extra_us=tuple(t - cfg.t0_us for t in times)))
    gt = {int(t): truth.gt_images[i] for i, t in enumerate(truth.gt_t_us)}
    oracle = Oracle(sim, c)
    res: dict[str, dict[str, float]] = {}
    mids = sim.mid_exposure_us
    for m, run in runs.items():
        keep = [i for i, t in enumerate(run.times) if skip <= t < last]
        ts = run.times[keep]
        imgs = [run.images[i] for i in keep]
        refs = run.refs[keep]
        g = [gt[int(t)] for t in ts]
        row = {"frames": len(ts), "psnr": np.mean([psnr(a, b) for a, b in zip(imgs, g)]),
               "ssim": np.mean([ssim(a, b) for a, b in zip(imgs, g)])}
        ks = reference_index(mids, refs)
        own = [oracle.image(int(t), int(k)) for t, k in zip(ts, ks)]  # true c
        row["psnr_own_oracle_truth"] = np.mean([psnr(a, b) for a, b in zip(own, g)])
        row["dn_vs_own_oracle"] = np.mean([np.mean(np.abs(a.astype(np.float64) - b)) for a, b in zip(imgs, own)])
        switch = refs[1:] != refs[:-1]
        row["consistency"] = consistency(ts, imgs, g, switch)
        # sensor-time latency: a frame rendered from a later APS frame waited until that frame's exposure ended
        ends = oracle.ends[ks]
        wait_ms = np.where(refs > ts, (ends - ts) / 1e3, 0.0)
        row["wait_mean_ms"], row["wait_max_ms"] = float(np.mean(wait_ms)), float(np.max(wait_ms))
        row["ms_per_latent"] = run.wall_ms_per_latent
        res[m] = row
    # the oracles at every scored time (the union of the modes' times)
    for name, pick in (("oracle causal", oracle.causal), ("oracle previous", oracle.previous),
                       ("oracle nearest", oracle.nearest)):
        imgs = [oracle.image(t, pick(t)) for t in times]
        g = [gt[t] for t in times]
        res[name] = {"frames": len(times), "psnr": np.mean([psnr(a, b) for a, b in zip(imgs, g)]),
                     "ssim": np.mean([ssim(a, b) for a, b in zip(imgs, g)])}
    log(f"# {label}: " + ", ".join(f"{m} {r['psnr']:.2f}" for m, r in res.items()))
    return res


def cost_ratio(sim: Simulation, every: int, repeats: int = 5,
               runs: tuple[tuple[str, int | None], ...] | None = None) -> dict[str, list[float]]:
    """Worker CPU ms per latent frame of each (mode, joint pairs) run, alternately `repeats` times (A/B in one
    run), after one untimed run of each (kernels compiled or loaded from the cache). Joint pairs None: the true c
    given; an int K: c estimated, with joint c over K pairs (0 = off)."""
    runs = runs or tuple((m, None) for m in MODES_RUN)
    c = true_c(sim)

    def one(mode: str, k: int | None) -> float:
        return feed_worker(sim, mode, every, c if k is None else None, k or 0).cpu_ms_per_latent

    for m, k in runs:
        one(m, k)
    out: dict[str, list[float]] = {m if k is None else f"{m}, c est. K={k}": [] for m, k in runs}
    for _ in range(repeats):
        for (m, k), name in zip(runs, out):
            out[name].append(one(m, k))
    return out


def modes_suite(quick: bool, realistic: bool):
    from tools.accuracy_harness import scene_suite
    from tools.bench_realistic import realistic_suite

    if realistic:
        return [(label, cfg) for group, label, cfg in realistic_suite(quick) if group == "mix" or quick]
    return [(label, cfg) for label, cfg in scene_suite(quick) if not label.startswith("static")]


def true_c(sim: Simulation) -> tuple[float, float]:
    cam = sim.camera()
    return float(cam["c_on"]), float(cam["c_off"])


def table(results: dict[str, dict[str, dict[str, float]]]) -> str:
    names = list(next(iter(results.values())))
    lines = ["| output | PSNR latent (dB) | SSIM latent | true-c oracle from the frame's ref_t (dB) | "
             "mean abs(node - that oracle) (DN) | "
             "temporal consistency (switch / elsewhere) | wait for a later APS frame, mean / max (ms, sensor time) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for n in names:
        rows = [per[n] for per in results.values()]

        def mean(key: str, fmt: str) -> str:
            vals = [r[key] for r in rows if key in r and np.isfinite(r[key])]
            return format(float(np.mean(vals)), fmt) if vals else "-"
        lines.append(f"| {n} | {mean('psnr', '.2f')} | {mean('ssim', '.3f')} | {mean('psnr_own_oracle_truth', '.2f')}"
                     f" | {mean('dn_vs_own_oracle', '.3f')} | {mean('consistency', '.2f')} | "
                     f"{mean('wait_mean_ms', '.1f')} / {mean('wait_max_ms', '.1f')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.bench_modes", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--realistic", action="store_true", help="the realistic-camera scenes (c: the true means)")
    ap.add_argument("--every", type=int, default=2000)
    ap.add_argument("--modes", default=",".join(MODES_RUN))
    ap.add_argument("--cost", action="store_true", help="only the CPU cost per latent frame of each mode, A/B")
    ap.add_argument("--repeats", type=int, default=9, help="--cost: alternating runs of each mode")
    ap.add_argument("--estimate-c", default="", help="also run each mode with c estimated, joint c over K pairs "
                                                     "for each comma-separated K (0 = single-pair policy)")
    args = ap.parse_args(argv)
    if args.cost:
        label, cfg = modes_suite(True, False)[0]
        from edi_live.fused_mode import JOINT_PAIRS

        sim = simulate(cfg)
        for title, runs in (("true c given", None),
                            ("c estimated", (("causal", 0), ("fused", 0), ("fused", JOINT_PAIRS),
                                             ("fused+residual", JOINT_PAIRS)))):
            cpu = cost_ratio(sim, args.every, args.repeats, runs)
            base = next(iter(cpu.values()))
            print(f"worker CPU ms per latent frame on '{label}' (--every {args.every}), {title}, median [min, max] "
                  f"of {args.repeats} alternating runs")
            for m, v in cpu.items():
                ratios = [a / b for a, b in zip(v, base)]
                print(f"  {m}: {np.median(v):.3f} [{min(v):.3f}, {max(v):.3f}] ms, x{np.median(ratios):.2f} causal "
                      f"[{min(ratios):.2f}, {max(ratios):.2f}]")
        return 0
    t0 = time.perf_counter()
    results = {}
    for label, cfg in modes_suite(args.quick, args.realistic):
        sim = simulate(cfg)
        results[label] = score_scene(label, sim, every=args.every, modes=tuple(args.modes.split(",")),
                                     c=true_c(sim), estimate_c=tuple(int(k) for k in args.estimate_c.split(",") if k))
    print(table(results))
    print(f"\nwall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
