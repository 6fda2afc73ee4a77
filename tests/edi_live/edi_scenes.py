"""Small scenes for the EDI tests, made by the package's simulator (edi_live.simulation): a texture translating
at constant velocity, events from ESIM threshold crossings, APS frames = mean LINEAR intensity over the
exposure, ground truth = the sharp frame at mid-exposure. Intensities on the 8-bit scale (0..255), times in
µs from 0. This module only translates the tests' vocabulary into a SceneConfig.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from edi_live.datatypes import Frame
from edi_live.simulation import SceneConfig, simulate
from edi_live.simulation.motion import Renderer


@dataclass
class Scene:
    width: int
    height: int
    c_on: float
    c_off: float
    events: np.ndarray
    frames: list[Frame]
    sharp_mid: list[np.ndarray]  # ground truth L(f) per frame, float32, 8-bit scale
    render: Callable[[float], np.ndarray]  # render(t_us) -> float32 linear intensity (8-bit scale)
    config: SceneConfig


def make_scene(tex: str = "brick", *, width: int = 64, height: int = 48, c_on: float = 0.25,
               c_off: float | None = None, velocity_px_per_ms: tuple[float, float] = (0.5, 0.2),
               exposure_us: int = 8000, period_us: int = 20000, n_frames: int = 3, sigma_c: float = 0.0,
               dt_us: int = 25, lo: float = 0.08, hi: float = 0.9, noise_hz: float = 0.0, hot_pixels: int = 0,
               hot_rate_hz: float = 2000.0, seed: int = 0) -> Scene:
    """n_frames APS frames, one every period_us, exposures centred in their periods; dt_us is the render
    grid when it divides the APS timing. Each pixel's reference level starts at a random phase (a real
    pixel's was set by its last event, long before the scene starts)."""
    c_off = c_on if c_off is None else c_off
    first = (period_us - exposure_us) // 2
    grid = math.gcd(math.gcd(exposure_us, period_us), first or exposure_us)
    cfg = SceneConfig(width=width, height=height, duration_s=n_frames * period_us * 1e-6, texture=tex, seed=seed,
                      intensity_range=(lo, hi), velocity_px_s=(1000.0 * velocity_px_per_ms[0],
                                                               1000.0 * velocity_px_per_ms[1]),
                      c_on=c_on, c_off=c_off, c_sigma=sigma_c, noise_rate_hz=noise_hz, hot_pixels=hot_pixels,
                      hot_rate_hz=hot_rate_hz, frame_interval_us=period_us, exposure_us=exposure_us,
                      first_exposure_us=first, latent_per_interval=0, step_us=dt_us if grid % dt_us == 0 else 0,
                      t0_us=0, ref_jitter=0.5, texture_anchor="centre",
                      texture_stretch=(1.0, 99.0))
    sim = simulate(cfg)
    renderer = Renderer(cfg)

    def render(t_us: float) -> np.ndarray:
        return (255.0 * np.exp(renderer.log_frame(t_us * 1e-6).astype(np.float64))).astype(np.float32)

    sharp = [sim.gt_images[int(np.flatnonzero((sim.gt_kind == 0) & (sim.gt_frame == i))[0])]
             for i in range(len(sim.frames))]
    return Scene(width, height, c_on, c_off, sim.events, sim.frames, sharp, render, cfg)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.clip(a, 0, 255).astype(np.float64) - b) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))
