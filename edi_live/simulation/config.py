"""What defines one simulated recording: `SceneConfig`, the named scene presets and their validation.

Every realistic camera effect is a field here whose default switches it off, so an ideal-camera config reads
and simulates exactly as before the effects existed. `camera.py` owns the effects' documented DAVIS values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

RESOLUTIONS = {"240x180": (240, 180), "346x260": (346, 260)}


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
    noise_rate_hz: float = 0.0  # background events per pixel per second, independent of the light
    hot_pixels: int = 0
    hot_rate_hz: float = 2000.0
    # APS
    frame_interval_us: int = 50_000
    exposure_us: int = 30_000
    first_exposure_us: int = 10_000  # start of the first exposure, relative to t0
    aps_noise_dn: float = 0.0  # Gaussian read noise before 8-bit rounding (DN)
    aps_offset_dn: float = 0.0  # black level added to the APS value (a real APS is not offset-free)
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
    # --- realistic-camera fields added later: written to the ground truth only when set (see output.py)
    shot_noise_hz: float = 0.0  # extra background rate per pixel in the dark: rate = this * min(1, dark/I)
    shot_noise_dark: float = 0.1  # linear intensity (fraction of full scale) at and below which it is full
    flicker_hz: float = 0.0  # a lamp whose intensity is modulated at this frequency (100/120 Hz mains); 0 = none
    flicker_depth: float = 0.4  # lamp intensity = level * (1 + depth * sin(2 pi f t))
    flicker_level: float = 0.55  # the lamp's mean linear intensity (fraction of full scale)
    flicker_region: tuple[float, float, float] = (0.72, 0.3, 0.14)  # centre x, y (fractions of w, h), radius (of h)
    texture_anchor: str = "top-left"  # where a photograph is cropped: "top-left" or "centre"
    texture_stretch: tuple[float, float] = (0.0, 100.0)  # texture percentiles mapped onto intensity_range
    ref_jitter: float = 0.0  # initial reference level offset, uniform +/- ref_jitter * min(c_on, c_off) per pixel
    effects: tuple[str, ...] = ()  # the named camera effects switched on (camera.EFFECTS), for the record
    # colour (colour_scene.py): a Bayer pattern ("RGGB" = DAVIS346 colour) makes an RGB scene seen through it
    color_filter: str | None = None
    color_c_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)  # (B, G, R) factors on each channel's thresholds


# fields that the ground-truth file leaves out while they hold their default (files stay as they were)
LATER_FIELDS = ("shot_noise_hz", "shot_noise_dark", "flicker_hz", "flicker_depth", "flicker_level",
                "flicker_region", "texture_anchor", "texture_stretch", "ref_jitter", "effects", "color_filter",
                "color_c_scale")

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
    # every realistic camera effect of camera.EFFECTS at its documented DAVIS value
    "realistic": dict(duration_s=0.6, texture="blocks", velocity_px_s=(200.0, 50.0), effects=("all",)),
    # a colour DAVIS346 (RGGB mosaic) looking at coloured blocks, with every realistic effect
    "colour": dict(width=346, height=260, duration_s=0.6, texture="blocks", velocity_px_s=(200.0, 50.0),
                   color_filter="RGGB", effects=("all",)),
}


def validate(cfg: SceneConfig) -> None:
    """ValueError with one line naming the bad setting."""
    if cfg.exposure_us <= 0 or cfg.frame_interval_us <= 0 or cfg.exposure_us > cfg.frame_interval_us:
        raise ValueError("need 0 < exposure_us <= frame_interval_us")
    if not (cfg.c_on > 0 and cfg.c_off > 0 and math.isfinite(cfg.c_on) and math.isfinite(cfg.c_off)):
        raise ValueError(f"contrast thresholds must be positive numbers (got c_on={cfg.c_on}, c_off={cfg.c_off})")
    if not cfg.duration_s > 0:
        raise ValueError(f"duration_s must be > 0 (got {cfg.duration_s})")
    for name in ("duration_s", "rotation_deg_s", "zoom_per_s", "oscillation_period_s", "c_sigma", "aps_noise_dn",
                 "aps_offset_dn", "aps_gamma", "flicker_hz", "flicker_depth", "noise_rate_hz", "hot_rate_hz",
                 "shot_noise_hz"):
        if not math.isfinite(getattr(cfg, name)):  # inf reached int() deep inside: an OverflowError traceback
            raise ValueError(f"{name} must be a finite number (got {getattr(cfg, name)})")
    if not all(math.isfinite(v) for v in cfg.velocity_px_s):
        raise ValueError(f"velocity_px_s must be finite numbers (got {cfg.velocity_px_s})")
    if cfg.latent_per_interval < 0:
        raise ValueError(f"latent_per_interval must be >= 0 (got {cfg.latent_per_interval})")
    for name in ("noise_rate_hz", "hot_rate_hz", "hot_pixels", "c_sigma", "refractory_us", "aps_noise_dn",
                 "shot_noise_hz", "flicker_hz", "ref_jitter", "aps_offset_dn"):
        if not getattr(cfg, name) >= 0:  # also catches NaN
            raise ValueError(f"{name} must be >= 0 (got {getattr(cfg, name)})")
    if cfg.texture_anchor not in ("top-left", "centre"):
        raise ValueError(f"texture_anchor must be 'top-left' or 'centre' (got {cfg.texture_anchor!r})")
    if cfg.color_filter is not None and cfg.color_filter not in ("RGGB", "GRBG", "GBRG", "BGGR"):
        raise ValueError(f"color_filter must be a Bayer pattern RGGB/GRBG/GBRG/BGGR or None (got {cfg.color_filter!r})")
    if len(cfg.color_c_scale) != 3 or not min(cfg.color_c_scale) > 0:
        raise ValueError(f"color_c_scale must be three positive factors (B, G, R) (got {cfg.color_c_scale})")
    if not cfg.aps_gamma > 0:
        raise ValueError(f"aps_gamma must be > 0 (got {cfg.aps_gamma})")
    if not 0 < cfg.shot_noise_dark <= 1:
        raise ValueError(f"shot_noise_dark must be in (0, 1] (got {cfg.shot_noise_dark})")
    if cfg.flicker_hz > 0:
        if not 0 <= cfg.flicker_depth < 1:
            raise ValueError(f"flicker_depth must be in [0, 1) (got {cfg.flicker_depth})")
        if not 0 < cfg.flicker_level * (1 + cfg.flicker_depth) <= 1:
            raise ValueError("the lamp must stay within the APS range: 0 < flicker_level*(1+flicker_depth) <= 1")


def check_memory(cfg: SceneConfig, n_frames: int, n_gt: int, channels: int, available: int | None) -> None:
    """ValueError, before anything is rendered, when the APS accumulators and ground-truth images (float32, held
    in memory until the end) would not fit in `available` bytes: such a run was killed by the kernel, or ground
    for hours, after the user had waited. `available` None: unknown, nothing is checked."""
    if available is None:
        return
    pixels = cfg.width * cfg.height
    need = 4 * pixels * (n_frames + n_gt * channels)
    if need > available:
        raise ValueError(f"{n_frames} APS frames and {n_gt} ground-truth images of {cfg.width}x{cfg.height} would "
                         f"need {need / 2**30:.1f} GiB of memory, {available / 2**30:.1f} GiB are free: give a "
                         f"shorter duration_s, fewer latent_per_interval, or no ground truth")
