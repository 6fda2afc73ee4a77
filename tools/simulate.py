"""ESIM-style DAVIS simulator: a moving textured scene -> events, blurred APS frames and sharp ground truth.

Owns the synthetic data that the EDI tests and `tools/bench_accuracy.py` measure against.

Scene model (one consistent definition, so every output agrees with every other):
- A texture (linear intensity in (0, 1], strictly positive) on a canvas is warped by a time-varying affine
  motion (translation, rotation, zoom; `cv2.warpAffine`, sub-pixel) and rendered at a uniform time grid
  t_k = k * step_us. Between two grid samples the LOG intensity of each pixel is linear in time.
- Events: ESIM's rule. Each pixel keeps a reference log level; every crossing of ref +/- its own threshold
  (per-pixel mismatch, separate ON/OFF thresholds) emits one event with a linearly interpolated timestamp.
  An optional refractory period drops events while the reference still advances (as ESIM does).
- APS frames: the exact time average of the linear intensity exp(log I(t)) over the exposure window
  (closed form per grid segment), scaled to 0..255, optional Gaussian read noise, rounded to 8 bits.
- Ground truth: exp(log I(t)) at mid-exposure of every frame and at latent times between frames, float32
  on the same 0..255 linear scale as the APS frames (not quantised).
- Noise: Poisson background events and hot pixels, added after the signal events (they do not move the
  reference level, because they carry no scene information).

Python API (numpy in, numpy out): `SceneConfig`, `preset()`, `simulate()`, `make_texture()`,
`Simulation`, `write_aedat4()`, `save_ground_truth()`, `load_ground_truth()`.
CLI: `python tools/simulate.py OUT.aedat4 [--preset demo] [--resolution 240x180] ...` writes OUT.aedat4
(events + APS frames, IMU optional) and OUT.npz (ground truth) beside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, Frame  # noqa: E402
from edi_live.errors import EdiLiveError  # noqa: E402

RESOLUTIONS = {"240x180": (240, 180), "346x260": (346, 260)}
PROCEDURAL_TEXTURES = ("blocks", "noise", "stripes")
SKIMAGE_TEXTURES = ("camera", "astronaut", "brick", "grass", "gravel", "moon", "coins", "text")


@dataclass
class SceneConfig:
    """Everything that defines one simulated recording. Times in µs unless the name says otherwise."""

    width: int = 240
    height: int = 180
    duration_s: float = 1.0
    texture: str = "blocks"
    seed: int = 0
    intensity_range: tuple[float, float] = (0.05, 0.95)  # linear, fraction of APS full scale
    # motion: position = v*t (or v*P/2pi*sin(2pi t/P) with an oscillation period P), angle = w*t, scale = exp(z*t)
    velocity_px_s: tuple[float, float] = (250.0, 60.0)
    rotation_deg_s: float = 0.0
    zoom_per_s: float = 0.0
    oscillation_period_s: float = 0.0  # 0 = constant velocity
    # event camera
    c_on: float = 0.2
    c_off: float = 0.2
    c_sigma: float = 0.03  # per-pixel threshold mismatch (absolute, log units)
    refractory_us: int = 0
    noise_rate_hz: float = 0.0  # background events per pixel per second
    hot_pixels: int = 0
    hot_rate_hz: float = 2000.0
    # APS
    frame_interval_us: int = 50_000
    exposure_us: int = 30_000
    first_exposure_us: int = 10_000  # start of the first exposure, relative to t0
    aps_noise_dn: float = 0.0  # Gaussian read noise before 8-bit rounding (DN)
    aps_offset_dn: float = 0.0  # dark offset added to the APS value (a real APS is not offset-free)
    aps_gamma: float = 1.0  # APS response 255*(I/255)**(1/gamma); 1 = linear, as EDI assumes
    event_offset_us: int = 0  # added to every event timestamp (DVS/APS clock misalignment)
    latent_per_interval: int = 4  # ground-truth latent frames between consecutive mid-exposures
    gt_extra_us: tuple[int, ...] = ()  # more ground-truth times (µs after t0), e.g. the times a node emits
    ground_truth: bool = True  # False: no sharp frames (long recordings: they cost H*W*4 bytes each)
    # rendering
    step_us: int = 0  # render grid; 0 = automatic (<= max_step_px of motion per step)
    max_step_px: float = 0.25
    t0_us: int = 1_700_000_000_000_000  # Unix-like µs, large on purpose (64-bit time everywhere)
    imu: bool = False


PRESETS: dict[str, dict] = {
    # README's first command: short, blurry, DAVIS240-sized, a few seconds of CPU
    "demo": dict(duration_s=1.5, texture="blocks", velocity_px_s=(400.0, 100.0), rotation_deg_s=15.0,
                 oscillation_period_s=2.0, exposure_us=30_000, frame_interval_us=50_000,
                 noise_rate_hz=0.2, hot_pixels=2, hot_rate_hz=500.0),
    "static": dict(duration_s=1.0, texture="blocks", velocity_px_s=(0.0, 0.0), rotation_deg_s=0.0,
                   zoom_per_s=0.0, noise_rate_hz=1.0, hot_pixels=3, hot_rate_hz=1000.0),
    "translate": dict(duration_s=0.6, velocity_px_s=(300.0, 0.0)),
    "rotate": dict(duration_s=0.6, velocity_px_s=(0.0, 0.0), rotation_deg_s=120.0),
    "zoom": dict(duration_s=0.6, velocity_px_s=(0.0, 0.0), zoom_per_s=0.8),
    "fast": dict(duration_s=0.6, velocity_px_s=(600.0, 150.0), rotation_deg_s=30.0),
    "noisy": dict(duration_s=0.6, noise_rate_hz=5.0, hot_pixels=10, hot_rate_hz=3000.0, aps_noise_dn=1.0),
    "davis346": dict(width=346, height=260, duration_s=1.0, texture="camera", velocity_px_s=(200.0, 80.0),
                     rotation_deg_s=20.0, oscillation_period_s=1.0),
}


def preset(name: str, **overrides) -> SceneConfig:
    """A named scene (see PRESETS) with keyword overrides, e.g. preset("translate", c_on=0.3)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    cfg = SceneConfig(**PRESETS[name])
    return dataclasses.replace(cfg, **overrides)


# --------------------------------------------------------------------------------------------- textures

def _smooth_noise(rng: np.random.Generator, h: int, w: int, cell: float) -> np.ndarray:
    small = rng.random((max(2, int(h / cell) + 2), max(2, int(w / cell) + 2))).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _procedural(name: str, h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    if name == "noise":  # fractal value noise: dense texture at several scales
        img = sum(_smooth_noise(rng, h, w, cell) * amp for cell, amp in ((64, 1.0), (24, 0.6), (8, 0.4), (3, 0.25)))
    elif name == "stripes":
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        img = np.zeros((h, w), np.float32)
        for _ in range(4):
            ang, per = rng.uniform(0, np.pi), rng.uniform(12, 48)
            img += np.sign(np.sin((xx * np.cos(ang) + yy * np.sin(ang)) * 2 * np.pi / per + rng.uniform(0, 6.3)))
    elif name == "blocks":  # random rectangles and disks: sharp edges that blur visibly, plus a little texture
        img = np.full((h, w), 0.5, np.float32)
        n = int(h * w / 900) + 10
        for _ in range(n):
            val = float(rng.uniform(0, 1))
            cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
            size = int(rng.integers(6, 40))
            if rng.random() < 0.6:
                cv2.rectangle(img, (cx - size, cy - size // 2), (cx + size, cy + size // 2), val, -1)
            else:
                cv2.circle(img, (cx, cy), size // 2, val, -1)
        img += 0.15 * (_smooth_noise(rng, h, w, 6) - 0.5)
    else:
        raise ValueError(f"unknown procedural texture {name!r}")
    return img.astype(np.float32)


def _skimage_texture(name: str) -> np.ndarray:
    try:
        from skimage import data  # test extra: only needed for these textures
    except ImportError as exc:
        raise ValueError(f"texture {name!r} needs scikit-image (pip install -e '.[test]'); "
                         f"procedural textures {PROCEDURAL_TEXTURES} need nothing") from exc
    img = getattr(data, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    img = img.astype(np.float32)
    return img / max(float(img.max()), 1e-6)


def make_texture(name: str, height: int, width: int, *, seed: int = 0,
                 intensity_range: tuple[float, float] = (0.05, 0.95)) -> np.ndarray:
    """A float32 (height, width) texture with linear intensities in `intensity_range` (strictly positive).

    Procedural names ("blocks", "noise", "stripes") use numpy only; scikit-image names ("camera",
    "astronaut", "brick", "grass", ...) are resized/tiled to the canvas. A light blur (optics) keeps the
    texture band-limited so sub-pixel warps and log-linear interpolation between render steps are accurate.
    """
    rng = np.random.default_rng(seed)
    if name in PROCEDURAL_TEXTURES:
        img = _procedural(name, height, width, rng)
    elif name in SKIMAGE_TEXTURES:
        src = _skimage_texture(name)
        scale = max(height / src.shape[0], width / src.shape[1], 1.0)
        if scale > 1.0:
            src = cv2.resize(src, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        img = src[:height, :width]
    else:
        raise ValueError(f"unknown texture {name!r}; choose from {PROCEDURAL_TEXTURES + SKIMAGE_TEXTURES}")
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    lo, hi = intensity_range
    mn, mx = float(img.min()), float(img.max())
    img = (img - mn) / max(mx - mn, 1e-6)
    return (lo + (hi - lo) * img).astype(np.float32)


# --------------------------------------------------------------------------------------------- rendering

class _Renderer:
    """Renders log intensity at any time (seconds after t0) by warping the canvas texture."""

    def __init__(self, cfg: SceneConfig):
        self.cfg = cfg
        w, h = cfg.width, cfg.height
        v = math.hypot(*cfg.velocity_px_s)
        reach = v * (cfg.oscillation_period_s / math.pi if cfg.oscillation_period_s > 0 else cfg.duration_s)
        margin = int(min(reach, 4 * max(w, h))) + max(w, h) // 2 + 8
        self.canvas_w, self.canvas_h = w + 2 * margin, h + 2 * margin
        self.texture = make_texture(cfg.texture, self.canvas_h, self.canvas_w, seed=cfg.seed,
                                    intensity_range=cfg.intensity_range)
        self.log_texture = np.log(self.texture)

    def matrix(self, t_s: float) -> np.ndarray:
        """2x3 affine map from output pixel coordinates to canvas coordinates at time t_s."""
        cfg = self.cfg
        vx, vy = cfg.velocity_px_s
        if cfg.oscillation_period_s > 0:
            k = cfg.oscillation_period_s / (2 * math.pi) * math.sin(2 * math.pi * t_s / cfg.oscillation_period_s)
            dx, dy = vx * k, vy * k
        else:
            dx, dy = vx * t_s, vy * t_s
        theta = math.radians(cfg.rotation_deg_s * t_s)
        scale = math.exp(cfg.zoom_per_s * t_s)
        a, b = math.cos(theta) / scale, math.sin(theta) / scale
        cxo, cyo = (cfg.width - 1) / 2, (cfg.height - 1) / 2
        cxc, cyc = (self.canvas_w - 1) / 2 + dx, (self.canvas_h - 1) / 2 + dy
        # q = C + R(theta)/s (p - c)
        return np.array([[a, -b, cxc - a * cxo + b * cyo], [b, a, cyc - b * cxo - a * cyo]], np.float64)

    def log_frame(self, t_s: float) -> np.ndarray:
        out = cv2.warpAffine(self.log_texture, self.matrix(t_s), (self.cfg.width, self.cfg.height),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT_101)
        return out  # float32: per-step work is float32, accumulators float64

    def max_speed_px_s(self) -> float:
        cfg = self.cfg
        r = math.hypot(cfg.width, cfg.height) / 2
        return math.hypot(*cfg.velocity_px_s) + abs(math.radians(cfg.rotation_deg_s)) * r \
            + abs(cfg.zoom_per_s) * r * math.exp(abs(cfg.zoom_per_s) * cfg.duration_s)


def _choose_step_us(cfg: SceneConfig, speed_px_s: float) -> int:
    g = math.gcd(math.gcd(cfg.exposure_us, cfg.frame_interval_us), max(cfg.first_exposure_us, 0) or cfg.exposure_us)
    if cfg.step_us:
        if g % cfg.step_us:
            raise ValueError(f"step_us={cfg.step_us} must divide exposure, frame interval and first exposure ({g} µs)")
        return cfg.step_us
    want = 1000.0 if speed_px_s <= 0 else min(1000.0, cfg.max_step_px / speed_px_s * 1e6)
    best = 1
    for d in range(1, int(math.isqrt(g)) + 1):
        if g % d == 0:
            for cand in (d, g // d):
                if cand <= want and cand > best:
                    best = cand
    return best


# --------------------------------------------------------------------------------------------- simulation

@dataclass
class Simulation:
    """Result of `simulate()`. Event times and frame windows are absolute µs (t0_us + offset)."""

    config: SceneConfig
    events: np.ndarray  # EVENT_DTYPE, time-ordered, signal + noise
    is_noise: np.ndarray  # bool per event: background or hot-pixel event
    frames: list[Frame]  # APS frames (uint8), exposure windows on the grid
    aps_linear: np.ndarray  # (n_frames, H, W) float32: exact exposure means on 0..255, before noise/rounding
    gt_t_us: np.ndarray  # (n_gt,) int64 ground-truth times
    gt_images: np.ndarray  # (n_gt, H, W) float32 sharp linear intensity on 0..255
    gt_kind: np.ndarray  # (n_gt,) int8: 0 = mid-exposure of frame gt_frame[i], 1 = latent after it, 2 = extra
    gt_frame: np.ndarray  # (n_gt,) int32: index of the APS frame whose mid-exposure precedes (or is) t; -1 none
    c_on_map: np.ndarray  # (H, W) float32 per-pixel ON thresholds actually used
    c_off_map: np.ndarray
    hot_pixel_xy: np.ndarray  # (n_hot, 2) int
    step_us: int
    imu: np.ndarray = field(default_factory=lambda: np.zeros(0, IMU_DTYPE))
    wall_s: float = 0.0

    @property
    def mid_exposure_us(self) -> np.ndarray:
        return np.array([(f.exposure_start_us + f.exposure_end_us) // 2 for f in self.frames], np.int64)

    def gt_at(self, t_us: int) -> np.ndarray:
        i = int(np.flatnonzero(self.gt_t_us == t_us)[0])
        return self.gt_images[i]


def _signal_events(ref: np.ndarray, l0: np.ndarray, l1: np.ndarray, con: np.ndarray, coff: np.ndarray,
                   t0_s: float, dt_s: float, refractory_s: float, last_t: np.ndarray):
    """ESIM crossings of the log level moving linearly l0 -> l1 over [t0_s, t0_s + dt_s].

    Updates `ref` (and `last_t` for the refractory period) in place; returns (pixel index, time s, polarity).
    """
    d = l1 - ref
    idx = np.flatnonzero((d >= con) | (d <= -coff))
    if idx.size == 0:
        return idx, np.zeros(0), np.zeros(0, bool)
    di = d[idx]
    on = di > 0
    n = np.where(on, np.floor(di / con[idx]), np.floor(-di / coff[idx])).astype(np.int64)
    keep_px = n > 0
    idx, on, n = idx[keep_px], on[keep_px], n[keep_px]
    counts = n
    step = np.where(on, con[idx], -coff[idx])
    total = int(counts.sum())
    pix = np.repeat(idx, counts)
    k = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    levels = ref[pix] + k * np.repeat(step, counts)
    dl = l1[pix] - l0[pix]
    frac = np.clip((levels - l0[pix]) / np.where(dl == 0, 1.0, dl), 0.0, 1.0)
    t = t0_s + frac.astype(np.float64) * dt_s  # float64 seconds: µs-exact over long recordings
    pol = np.repeat(on, counts)
    ref[idx] += counts * step
    if refractory_s > 0:
        # within one step a pixel's crossings are evenly spaced by s; keep the greedy subset analytically
        s = np.repeat(np.abs(step) / np.maximum(np.abs(l1[idx] - l0[idx]), 1e-12) * dt_s, counts)
        t_first = np.repeat(t[np.cumsum(counts) - counts], counts)
        allowed = last_t[pix] + refractory_s
        k0 = np.maximum(1, np.ceil((allowed - t_first) / np.maximum(s, 1e-15) - 1e-9) + 1)
        m = np.maximum(1, np.ceil(refractory_s / np.maximum(s, 1e-15) - 1e-9))
        keep = (k >= k0) & (((k - k0) % m) == 0)
        pix, t, pol = pix[keep], t[keep], pol[keep]
        np.maximum.at(last_t, pix, t)
    return pix, t, pol


def _noise_events(cfg: SceneConfig, rng: np.random.Generator, duration_s: float):
    w, h = cfg.width, cfg.height
    n_bg = rng.poisson(cfg.noise_rate_hz * w * h * duration_s) if cfg.noise_rate_hz > 0 else 0
    pix = [rng.integers(0, w * h, n_bg)]
    t = [rng.random(n_bg) * duration_s]
    pol = [rng.random(n_bg) < 0.5]
    hot = rng.choice(w * h, size=min(cfg.hot_pixels, w * h), replace=False) if cfg.hot_pixels else np.zeros(0, int)
    for p in hot:
        n = rng.poisson(cfg.hot_rate_hz * duration_s)
        pix.append(np.full(n, p))
        t.append(rng.random(n) * duration_s)
        pol.append(rng.random(n) < rng.uniform(0.2, 0.8))
    xy = np.stack([hot % w, hot // w], axis=1) if hot.size else np.zeros((0, 2), int)
    return np.concatenate(pix), np.concatenate(t), np.concatenate(pol), xy


def _to_events(pix: np.ndarray, t_us: np.ndarray, pol: np.ndarray, width: int) -> np.ndarray:
    ev = np.empty(pix.size, EVENT_DTYPE)
    ev["t"] = t_us
    ev["x"] = pix % width
    ev["y"] = pix // width
    ev["p"] = pol
    return ev


def simulate(cfg: SceneConfig) -> Simulation:
    """Run the simulator. Deterministic for a given config (seed included)."""
    wall0 = time.perf_counter()
    if cfg.exposure_us <= 0 or cfg.frame_interval_us <= 0 or cfg.exposure_us > cfg.frame_interval_us:
        raise ValueError("need 0 < exposure_us <= frame_interval_us")
    if min(cfg.c_on, cfg.c_off) <= 0:
        raise ValueError("contrast thresholds must be positive")
    if not cfg.duration_s > 0:
        raise ValueError(f"duration_s must be > 0 (got {cfg.duration_s})")
    for name in ("noise_rate_hz", "hot_rate_hz", "hot_pixels", "c_sigma", "refractory_us", "aps_noise_dn"):
        if not getattr(cfg, name) >= 0:  # also catches NaN
            raise ValueError(f"{name} must be >= 0 (got {getattr(cfg, name)})")
    rng = np.random.default_rng(cfg.seed + 1)
    w, h = cfg.width, cfg.height
    renderer = _Renderer(cfg)
    step_us = _choose_step_us(cfg, renderer.max_speed_px_s())
    duration_us = int(round(cfg.duration_s * 1e6))
    n_steps = duration_us // step_us
    duration_us = n_steps * step_us

    floor_c = lambda c: max(0.25 * c, 0.01)  # noqa: E731 - a mismatch draw never makes a threshold vanish
    con = np.maximum(cfg.c_on + cfg.c_sigma * rng.standard_normal(w * h), floor_c(cfg.c_on)).astype(np.float32)
    coff = np.maximum(cfg.c_off + cfg.c_sigma * rng.standard_normal(w * h), floor_c(cfg.c_off)).astype(np.float32)

    # APS exposure windows (relative µs) fully inside the simulated time
    starts = np.arange(cfg.first_exposure_us, duration_us - cfg.exposure_us + 1, cfg.frame_interval_us, dtype=np.int64)
    ends = starts + cfg.exposure_us
    mids = (starts + ends) // 2
    # ground-truth times: each mid-exposure, then latent times between it and the next mid-exposure
    gt_t, gt_kind, gt_frame = [], [], []
    for i, m in enumerate(mids):
        gt_t.append(m), gt_kind.append(0), gt_frame.append(i)
        if i + 1 < len(mids):
            for j in range(1, cfg.latent_per_interval + 1):
                gt_t.append(m + (mids[i + 1] - m) * j // (cfg.latent_per_interval + 1))
                gt_kind.append(1), gt_frame.append(i)
    for t in cfg.gt_extra_us:
        if not 0 <= t <= duration_us:
            raise ValueError(f"ground-truth time {t} µs is outside the simulated 0..{duration_us} µs")
        gt_t.append(int(t)), gt_kind.append(2), gt_frame.append(int(np.searchsorted(mids, t, side="right")) - 1)
    if not cfg.ground_truth:
        gt_t, gt_kind, gt_frame = [], [], []
    order = np.argsort(np.array(gt_t, np.int64), kind="stable")
    gt_t = np.array(gt_t, np.int64)[order]
    gt_kind = [gt_kind[i] for i in order]
    gt_frame = [gt_frame[i] for i in order]
    gt_images = np.zeros((gt_t.size, h, w), np.float32)
    aps_linear = np.zeros((starts.size, h, w), np.float32)
    aps_acc: dict[int, np.ndarray] = {}  # only the exposures open right now (float64 accumulators)
    n_seg = cfg.exposure_us // step_us

    l0 = renderer.log_frame(0.0).ravel()
    ref = l0.copy()
    e0 = np.exp(l0)
    last_t = np.full(w * h, -np.inf)
    chunks_pix, chunks_t, chunks_pol = [], [], []
    gt_pos = 0
    for k in range(n_steps):
        ta, tb = k * step_us, (k + 1) * step_us
        l1 = renderer.log_frame(tb * 1e-6).ravel()
        pix, t_s, pol = _signal_events(ref, l0, l1, con, coff, ta * 1e-6, step_us * 1e-6,
                                       cfg.refractory_us * 1e-6, last_t)
        if pix.size:
            chunks_pix.append(pix), chunks_t.append(t_s), chunks_pol.append(pol)
        # exact mean of exp(log-linear) over this segment, added to every exposure that contains it
        active = np.flatnonzero((starts <= ta) & (ends >= tb))
        e1 = np.exp(l1)
        if active.size:
            dl = l1 - l0
            ratio = np.ones_like(dl)
            np.divide(np.expm1(dl), dl, out=ratio, where=np.abs(dl) > 1e-6)
            seg = e0 * ratio
            for a in active:
                if a in aps_acc:
                    aps_acc[a] += seg
                else:
                    aps_acc[a] = seg.astype(np.float64)
        for a in np.flatnonzero(ends == tb):
            aps_linear[a] = (255.0 * aps_acc.pop(int(a)) / n_seg).reshape(h, w)
        while gt_pos < gt_t.size and gt_t[gt_pos] <= tb:  # sorted, so each is rendered in its segment
            a = (gt_t[gt_pos] - ta) / step_us
            gt_images[gt_pos] = (255.0 * np.exp(l0 + a * (l1 - l0))).reshape(h, w)
            gt_pos += 1
        l0, e0 = l1, e1

    sig_pix = np.concatenate(chunks_pix) if chunks_pix else np.zeros(0, np.int64)
    sig_t = np.concatenate(chunks_t) if chunks_t else np.zeros(0)
    sig_pol = np.concatenate(chunks_pol) if chunks_pol else np.zeros(0, bool)
    nz_pix, nz_t, nz_pol, hot_xy = _noise_events(cfg, rng, duration_us * 1e-6)
    pix = np.concatenate([sig_pix, nz_pix])
    t_us = np.rint(np.concatenate([sig_t, nz_t]) * 1e6).astype(np.int64)
    pol = np.concatenate([sig_pol, nz_pol])
    is_noise = np.concatenate([np.zeros(sig_pix.size, bool), np.ones(nz_pix.size, bool)])
    order = np.argsort(t_us, kind="stable")
    events = _to_events(pix[order], t_us[order] + cfg.t0_us + cfg.event_offset_us, pol[order], w)
    is_noise = is_noise[order]

    frames = []
    for i in range(starts.size):
        img = aps_linear[i].astype(np.float64)
        if cfg.aps_gamma != 1.0:
            img = 255.0 * (img / 255.0) ** (1.0 / cfg.aps_gamma)
        img = img + cfg.aps_offset_dn
        if cfg.aps_noise_dn > 0:
            img = img + cfg.aps_noise_dn * rng.standard_normal(img.shape)
        img8 = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        frames.append(Frame(image=img8, exposure_start_us=int(starts[i] + cfg.t0_us),
                            exposure_end_us=int(ends[i] + cfg.t0_us), start_us=int(starts[i] + cfg.t0_us),
                            end_us=int(ends[i] + cfg.t0_us), seq=i))
    imu = _imu_samples(cfg, duration_us) if cfg.imu else np.zeros(0, IMU_DTYPE)
    return Simulation(config=cfg, events=events, is_noise=is_noise, frames=frames, aps_linear=aps_linear,
                      gt_t_us=gt_t + cfg.t0_us, gt_images=gt_images, gt_kind=np.array(gt_kind, np.int8),
                      gt_frame=np.array(gt_frame, np.int32), c_on_map=con.reshape(h, w),
                      c_off_map=coff.reshape(h, w), hot_pixel_xy=hot_xy, step_us=step_us,
                      imu=imu, wall_s=time.perf_counter() - wall0)


def _imu_samples(cfg: SceneConfig, duration_us: int, rate_hz: float = 200.0) -> np.ndarray:
    """Gyro z = the scene's rotation rate, accelerometer = gravity; enough for a stream that exists."""
    t = np.arange(0, duration_us, int(1e6 / rate_hz), dtype=np.int64)
    imu = np.zeros(t.size, IMU_DTYPE)
    imu["t"] = t + cfg.t0_us
    imu["temperature_c"] = 30.0
    imu["accel_g"][:, 1] = -1.0
    imu["gyro_dps"][:, 2] = cfg.rotation_deg_s
    return imu


# --------------------------------------------------------------------------------------------- output

def write_aedat4(sim: Simulation, path: str | Path, *, chunk_events: int = 20_000) -> None:
    """Write events and APS frames (and IMU if simulated) in time order through edi_live's Aedat4Writer.

    Each frame is written after every event up to its exposure end, as a camera would deliver it.
    """
    from edi_live.aedat4.writer import Aedat4Writer

    ev = sim.events
    cfg = sim.config
    with Aedat4Writer(path, cfg.width, cfg.height, events=True, frames=True, imu=bool(sim.imu.size),
                      camera_name="edi-live-sim") as wr:
        pos = 0
        imu_pos = 0
        bounds = [f.exposure_end_us for f in sim.frames] + [np.iinfo(np.int64).max]
        for i, bound in enumerate(bounds):
            stop = int(np.searchsorted(ev["t"], bound, side="right"))
            while pos < stop:
                nxt = min(stop, pos + chunk_events)
                wr.write_events(ev[pos:nxt])
                pos = nxt
            if sim.imu.size:
                istop = int(np.searchsorted(sim.imu["t"], bound, side="right"))
                if istop > imu_pos:
                    wr.write_imu(sim.imu[imu_pos:istop])
                    imu_pos = istop
            if i < len(sim.frames):
                wr.write_frame(sim.frames[i])


def save_ground_truth(sim: Simulation, path: str | Path) -> None:
    """Ground truth beside the recording: sharp frames, their times/kinds, thresholds and the config."""
    cfg = dataclasses.asdict(sim.config)
    np.savez_compressed(
        path, gt_t_us=sim.gt_t_us, gt_images=sim.gt_images, gt_kind=sim.gt_kind, gt_frame=sim.gt_frame,
        aps_images=np.stack([f.image for f in sim.frames]) if sim.frames else np.zeros((0, cfg["height"], cfg["width"]), np.uint8),
        aps_linear=sim.aps_linear,
        exposure_start_us=np.array([f.exposure_start_us for f in sim.frames], np.int64),
        exposure_end_us=np.array([f.exposure_end_us for f in sim.frames], np.int64),
        c_on_map=sim.c_on_map, c_off_map=sim.c_off_map, hot_pixel_xy=sim.hot_pixel_xy,
        n_events=np.int64(sim.events.size), n_noise_events=np.int64(sim.is_noise.sum()),
        config_json=json.dumps(cfg))


def load_ground_truth(path: str | Path) -> dict:
    """Inverse of save_ground_truth: a dict of arrays plus 'config' (dict)."""
    with np.load(path) as z:
        out = {k: z[k] for k in z.files}
    out["config"] = json.loads(str(out.pop("config_json")))
    return out


# --------------------------------------------------------------------------------------------- CLI

def _parse_pair(text: str, what: str) -> tuple[float, float]:
    try:
        a, b = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be two comma-separated numbers, e.g. 200,50") from None
    return a, b


def _help_epilog() -> str:
    """Where the defaults come from: the preset's settings over SceneConfig's, both listed from the code."""
    base = SceneConfig()
    shown = ("width", "height", "duration_s", "texture", "seed", "c_on", "c_off", "c_sigma", "velocity_px_s",
             "rotation_deg_s", "zoom_per_s", "oscillation_period_s", "exposure_us", "frame_interval_us",
             "refractory_us", "noise_rate_hz", "hot_pixels", "hot_rate_hz", "aps_noise_dn", "aps_offset_dn",
             "aps_gamma", "event_offset_us", "latent_per_interval")
    lines = ["defaults: an option not given takes its value from --preset (default demo), else from these",
             "(units in the names: _s seconds, _us microseconds, _hz per second, _px_s pixels per second, c in",
             "log-intensity units):",
             textwrap.fill(", ".join(f"{k}={getattr(base, k)}" for k in shown), 100, initial_indent="  ",
                           subsequent_indent="  "), "", "presets:"]
    for name in sorted(PRESETS):
        lines.append(textwrap.fill(", ".join(f"{k}={v}" for k, v in PRESETS[name].items()), 100,
                                   initial_indent=f"  {name}: ", subsequent_indent="      "))
    lines += ["", "examples:", "  python tools/simulate.py /tmp/demo.aedat4",
              "  python tools/simulate.py /tmp/cam.aedat4 --preset davis346 --c 0.3 --noise-rate-hz 0.5",
              "  python tools/simulate.py /tmp/long.aedat4 --preset fast --duration-s 10 --no-ground-truth"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python tools/simulate.py", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Simulate a DAVIS recording (events + blurry APS frames) of a moving texture; writes "
                    "OUT.aedat4 and the ground truth OUT.npz beside it.", epilog=_help_epilog())
    ap.add_argument("out", help="output .aedat4 path")
    ap.add_argument("--preset", default="demo", choices=sorted(PRESETS))
    ap.add_argument("--resolution", choices=sorted(RESOLUTIONS), help="240x180 (DAVIS240) or 346x260 (DAVIS346)")
    ap.add_argument("--duration-s", type=float)
    ap.add_argument("--texture", help=f"{', '.join(PROCEDURAL_TEXTURES + SKIMAGE_TEXTURES)} "
                                      "(scikit-image ones need the test extra)")
    ap.add_argument("--seed", type=int)
    ap.add_argument("--c", type=float, help="contrast threshold for ON and OFF")
    ap.add_argument("--c-on", type=float)
    ap.add_argument("--c-off", type=float)
    ap.add_argument("--c-sigma", type=float, help="per-pixel threshold mismatch (log units)")
    ap.add_argument("--velocity", type=lambda s: _parse_pair(s, "--velocity"), metavar="VX,VY",
                    help="translation in px/s")
    ap.add_argument("--rotation-deg-s", type=float)
    ap.add_argument("--zoom-per-s", type=float)
    ap.add_argument("--oscillation-period-s", type=float, help="0 = constant velocity")
    ap.add_argument("--exposure-us", type=int)
    ap.add_argument("--frame-interval-us", type=int)
    ap.add_argument("--refractory-us", type=int)
    ap.add_argument("--noise-rate-hz", type=float, help="background events per pixel per second")
    ap.add_argument("--hot-pixels", type=int)
    ap.add_argument("--hot-rate-hz", type=float)
    ap.add_argument("--aps-noise-dn", type=float, help="Gaussian read noise of the APS (DN)")
    ap.add_argument("--aps-offset-dn", type=float, help="dark offset of the APS (DN)")
    ap.add_argument("--aps-gamma", type=float, help="APS response gamma (1 = linear)")
    ap.add_argument("--event-offset-us", type=int, help="shift every event timestamp (DVS/APS misalignment)")
    ap.add_argument("--latent-per-interval", type=int)
    ap.add_argument("--gt-times-us", type=lambda v: tuple(int(x) for x in v.split(",")), metavar="T1,T2,...",
                    help="extra ground-truth times, µs after the start")
    ap.add_argument("--imu", action="store_true", help="also write an IMU stream")
    ap.add_argument("--no-ground-truth", action="store_true", help="do not write OUT.npz")
    args = ap.parse_args(argv)

    over: dict = {}
    if args.resolution:
        over["width"], over["height"] = RESOLUTIONS[args.resolution]
    simple = {"duration_s": args.duration_s, "texture": args.texture, "seed": args.seed, "c_sigma": args.c_sigma,
              "rotation_deg_s": args.rotation_deg_s, "zoom_per_s": args.zoom_per_s,
              "oscillation_period_s": args.oscillation_period_s, "exposure_us": args.exposure_us,
              "frame_interval_us": args.frame_interval_us, "refractory_us": args.refractory_us,
              "noise_rate_hz": args.noise_rate_hz, "hot_pixels": args.hot_pixels, "hot_rate_hz": args.hot_rate_hz,
              "aps_noise_dn": args.aps_noise_dn, "latent_per_interval": args.latent_per_interval,
              "aps_offset_dn": args.aps_offset_dn, "aps_gamma": args.aps_gamma,
              "event_offset_us": args.event_offset_us,
              "velocity_px_s": args.velocity, "gt_extra_us": args.gt_times_us}
    over.update({k: v for k, v in simple.items() if v is not None})
    if args.c is not None:
        over["c_on"] = over["c_off"] = args.c
    if args.c_on is not None:
        over["c_on"] = args.c_on
    if args.c_off is not None:
        over["c_off"] = args.c_off
    if args.imu:
        over["imu"] = True
    if args.no_ground_truth:
        over["ground_truth"] = False
    out = Path(args.out)
    if out.is_dir() or not out.resolve().parent.is_dir():  # say so now, not after the simulation
        print(f"simulate.py: error: cannot write {out}: "
              f"{'it is a directory' if out.is_dir() else 'its folder does not exist'}", file=sys.stderr)
        return 2
    try:
        cfg = preset(args.preset, **over)
        sim = simulate(cfg)
    except ValueError as exc:
        print(f"simulate.py: error: {exc}", file=sys.stderr)
        return 2
    try:
        write_aedat4(sim, out)
    except EdiLiveError as exc:  # e.g. no write permission
        print(f"simulate.py: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    if not args.no_ground_truth:
        save_ground_truth(sim, out.with_suffix(".npz"))
    print(f"{out}: {cfg.width}x{cfg.height}, {cfg.duration_s:g} s, {sim.events.size} events "
          f"({int(sim.is_noise.sum())} noise), {len(sim.frames)} APS frames "
          f"(exposure {cfg.exposure_us} µs every {cfg.frame_interval_us} µs), c_on={cfg.c_on:g} c_off={cfg.c_off:g}, "
          f"simulated in {sim.wall_s:.1f} s"
          + ("" if args.no_ground_truth else f"; ground truth in {out.with_suffix('.npz')}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
