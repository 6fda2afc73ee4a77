"""What every accuracy benchmark shares: the PSNR/SSIM metrics, the scene suite, the outputs of a method on a
scene with the milliseconds each cost, the blurry-frame baseline, EDI with given c on given frames, the streaming
reconstructor fed as the node feeds it, and the score of outputs against the simulator's ground truth.

Used by tools/bench_accuracy.py (the suite), tools/bench_modes.py, tools/bench_realistic.py and the reports;
none of those is imported here, so the benchmarks depend on this module and not on each other.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from edi_live.simulation import SKIMAGE_TEXTURES, SceneConfig, Simulation, preset
from tools import baselines as bl

cv2.setNumThreads(1)
_cpu = time.thread_time  # CPU time of this thread: other processes on a shared machine do not inflate it


# --------------------------------------------------------------------------------------------- metrics

def psnr(img: np.ndarray, ref: np.ndarray, data_range: float = 255.0) -> float:
    """PSNR in dB of img against ref, both clipped to [0, data_range]."""
    a = np.clip(np.asarray(img, np.float64), 0, data_range)
    b = np.clip(np.asarray(ref, np.float64), 0, data_range)
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * math.log10(data_range ** 2 / mse)


def ssim(img: np.ndarray, ref: np.ndarray, data_range: float = 255.0, win: int = 7) -> float:
    """Mean SSIM (Wang et al. 2004) with a uniform win x win window, K1=0.01, K2=0.03 and the sample
    covariance, averaged away from the borders: the same definition as skimage.metrics.structural_similarity
    with its defaults, written with cv2 box filters."""
    a = np.clip(np.asarray(img, np.float64), 0, data_range)
    b = np.clip(np.asarray(ref, np.float64), 0, data_range)
    n = win * win
    box = lambda z: cv2.blur(z, (win, win), borderType=cv2.BORDER_REFLECT_101)  # noqa: E731
    ux, uy = box(a), box(b)
    cov_norm = n / (n - 1.0)
    vx = cov_norm * (box(a * a) - ux * ux)
    vy = cov_norm * (box(b * b) - uy * uy)
    vxy = cov_norm * (box(a * b) - ux * uy)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    pad = (win - 1) // 2
    return float(s[pad:-pad, pad:-pad].mean())


# --------------------------------------------------------------------------------------------- scenes

def _texture(name: str) -> str:
    """scikit-image textures when installed (test extra), procedural ones otherwise."""
    if name in SKIMAGE_TEXTURES:
        try:
            import skimage.data  # noqa: F401
        except ImportError:
            return {"camera": "blocks", "astronaut": "blocks"}.get(name, "noise")
    return name


def scene_suite(quick: bool = False) -> list[tuple[str, SceneConfig]]:
    """(label, config) of every benchmark scene, 240x180 unless the label says 346."""
    d = 0.35 if quick else 0.5
    common = dict(duration_s=d, c_sigma=0.03, latent_per_interval=4, noise_rate_hz=0.1)
    scenes = [
        ("blocks translate c=0.2", preset("translate", texture=_texture("blocks"), velocity_px_s=(300.0, 40.0),
                                          c_on=0.2, c_off=0.2, seed=1, **common)),
        ("camera rot+transl c=0.2", preset("translate", texture=_texture("camera"), velocity_px_s=(200.0, 80.0),
                                           rotation_deg_s=40.0, c_on=0.2, c_off=0.2, seed=2, **common)),
        ("brick fast c=0.3", preset("fast", texture=_texture("brick"), c_on=0.3, c_off=0.3, seed=3, **common)),
        ("static + noise/hot c=0.2", preset("static", texture=_texture("camera"), seed=8,
                                            **{**common, "noise_rate_hz": 1.0}, hot_pixels=5, hot_rate_hz=1000.0)),
    ]
    if quick:
        return scenes
    scenes[3:3] = [
        ("grass zoom c=0.15", preset("zoom", texture=_texture("grass"), zoom_per_s=1.5, c_on=0.15, c_off=0.15,
                                     seed=4, **common)),
        ("astronaut rotate c_on=.25 c_off=.35", preset("rotate", texture=_texture("astronaut"), rotation_deg_s=200.0,
                                                       c_on=0.25, c_off=0.35, seed=5, **common)),
        ("gravel c=0.4 + noise/hot/read", preset("noisy", texture=_texture("gravel"), velocity_px_s=(300.0, -60.0), c_on=0.4,
                                                c_off=0.4, seed=6, **{**common, "noise_rate_hz": 5.0},
                                                hot_pixels=10, hot_rate_hz=3000.0, aps_noise_dn=1.0)),
        ("346x260 camera c=0.2", preset("davis346", texture=_texture("camera"), velocity_px_s=(300.0, 80.0),
                                        oscillation_period_s=0.0, c_on=0.2, c_off=0.2, seed=7,
                                        **common)),
    ]
    return scenes


def pitfall_suite() -> list[tuple[str, SceneConfig]]:
    """Opt-in scenes with the real-sensor pitfalls of the notes: EDI's model assumes none of them."""
    base = dict(texture=_texture("camera"), velocity_px_s=(250.0, 60.0), duration_s=0.5, noise_rate_hz=0.1, seed=11)
    return [
        ("pitfall: APS dark offset 8 DN", preset("translate", aps_offset_dn=8.0, **base)),
        ("pitfall: APS gamma 1.5", preset("translate", aps_gamma=1.5, **base)),
        ("pitfall: events 2 ms late", preset("translate", event_offset_us=2_000, **base)),
    ]


# --------------------------------------------------------------------------------------------- harness

@dataclass
class Outputs:
    """What one method produced on one scene: images keyed by ground-truth index, with the ms each cost."""

    deblurred: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)
    latent: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)
    note: str = ""


def _events_between(ev: np.ndarray, t0: int, t1: int, *, left: str = "right") -> np.ndarray:
    """Events with t0 < t <= t1 (left='right') or t0 <= t <= t1 (left='left')."""
    t = ev["t"]
    return ev[np.searchsorted(t, t0, side=left):np.searchsorted(t, t1, side="right")]


def _gt_targets(sim: Simulation) -> tuple[dict[int, int], dict[int, list[int]]]:
    """frame index -> gt index of its mid-exposure; frame index -> gt indices of latent times after it."""
    mids = {int(sim.gt_frame[i]): i for i in np.flatnonzero(sim.gt_kind == 0)}
    lat: dict[int, list[int]] = {}
    for i in np.flatnonzero(sim.gt_kind == 1):
        lat.setdefault(int(sim.gt_frame[i]), []).append(int(i))
    return mids, lat


def run_blurry(sim: Simulation) -> Outputs:
    out = Outputs()
    mids, lat = _gt_targets(sim)
    for k, f in enumerate(sim.frames):
        t0 = _cpu()
        img = bl.blurry(f)
        ms = (_cpu() - t0) * 1e3
        out.deblurred[mids[k]] = (img, ms)
        for g in lat.get(k, []):
            out.latent[g] = (img, 0.0)  # the newest frame stays on screen until the next one
    return out


def _edi_on(sim: Simulation, ev: np.ndarray, frames: list, c_on: float, c_off: float, out: Outputs) -> Outputs:
    """EDI with edi_live.edi's public functions on the given events and (B, informative) per APS frame: L(f) at
    every mid-exposure, then each ground-truth latent time propagated from it."""
    from edi_live import edi

    cfg = sim.config
    mids, lat = _gt_targets(sim)
    for k, (f, (b, informative)) in enumerate(zip(sim.frames, frames)):
        t0 = _cpu()
        table = edi.build_level_table(ev, cfg.width, cfg.height, f.exposure_start_us, f.exposure_end_us,
                                      segments=c_on != c_off)
        log_l = edi.deblur_log(b, table, c_on, c_off, informative=informative)
        out.deblurred[mids[k]] = (np.exp(log_l), (_cpu() - t0) * 1e3)
        state, t_state = log_l.copy(), table.ref_t_us
        for g in lat.get(k, []):
            t0 = _cpu()
            t = int(sim.gt_t_us[g])
            edi.propagate_log(state, _events_between(ev, t_state, t), c_on, c_off)
            t_state = t
            out.latent[g] = (np.exp(state), (_cpu() - t0) * 1e3)
    return out


def run_reconstructor(sim: Simulation, reconstructor=None, **kwargs) -> Outputs:
    """The streaming EdiReconstructor (made with `kwargs`, or the one given), fed like the node feeds it (causal
    latent frames)."""
    from edi_live.reconstructor import EdiReconstructor

    cfg = sim.config
    rec = EdiReconstructor(cfg.width, cfg.height, **kwargs) if reconstructor is None else reconstructor
    out = Outputs()
    mids, lat = _gt_targets(sim)
    ev = sim.events
    cs = []
    for k, f in enumerate(sim.frames):
        t0 = _cpu()
        off = int(rec.clock_offset_us)  # the exposure in the event clock (as the worker's gate and window)
        r = rec.on_frame(f, _events_between(ev, f.exposure_start_us + off, f.exposure_end_us + off, left="left"))
        out.deblurred[mids[k]] = (r.image.astype(np.float32), (_cpu() - t0) * 1e3)
        cs.append((r.c_on, r.c_off))
        t_applied = f.exposure_end_us + off
        for g in lat.get(k, []):
            t = int(sim.gt_t_us[g]) + off  # the ground truth's time in the event clock
            t0 = _cpu()
            if t <= t_applied:  # still inside this frame's exposure: go from the reference L(f)
                f_ev = f.mid_exposure_us + off
                r = rec.render_from_reference(t, _events_between(ev, min(t, f_ev), max(t, f_ev)))
            else:
                rec.on_events(_events_between(ev, t_applied, t))
                t_applied = t
                r = rec.render()
            out.latent[g] = (r.image.astype(np.float32), (_cpu() - t0) * 1e3)
    c = np.array(cs[1:] or cs)
    out.note = f"c_on={np.median(c[:, 0]):.3f} c_off={np.median(c[:, 1]):.3f} (median)"
    if hasattr(rec, "reestimations"):
        out.note += f", {rec.reestimations} re-est."
    return out


# --------------------------------------------------------------------------------------------- scoring

@dataclass
class Score:
    psnr_deblur: float
    ssim_deblur: float
    psnr_latent: float
    ssim_latent: float
    ms_deblur: float  # median per APS frame
    ms_latent: float  # median per latent frame
    note: str = ""
    ms_deblur_mean: float = float("nan")  # mean per APS frame: amortises occasional c re-estimations


def score(sim: Simulation, out: Outputs, *, skip_first: int = 1) -> Score:
    """Mean PSNR/SSIM over frames >= skip_first (the first frame warms up stateful methods)."""
    def agg(items: dict[int, tuple[np.ndarray, float]]):
        keep = [(g, v) for g, v in items.items() if sim.gt_frame[g] >= skip_first]
        if not keep:
            return float("nan"), float("nan"), float("nan"), float("nan")
        p = [psnr(img, sim.gt_images[g]) for g, (img, _) in keep]
        s = [ssim(img, sim.gt_images[g]) for g, (img, _) in keep]
        ms = [ms for _, (_, ms) in keep]
        return float(np.mean(p)), float(np.mean(s)), float(np.median(ms)), float(np.mean(ms))
    pd, sd, md, mdm = agg(out.deblurred)
    pl, sl, ml, _ = agg(out.latent)
    return Score(pd, sd, pl, sl, md, ml, out.note, mdm)
