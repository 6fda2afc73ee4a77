"""The moving scene: the texture on a canvas, warped by a time-varying affine motion, plus an optional
flickering lamp. Owns the scene's log intensity at any time and the choice of the render time grid.

Between two grid samples the LOG intensity of each pixel is linear in time; every output (events, APS
frames, ground truth) uses that one definition.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from edi_live.simulation import colour_scene
from edi_live.simulation.config import SceneConfig
from edi_live.simulation.texture import make_texture

FLICKER_STEPS_PER_PERIOD = 40  # render samples per lamp period: the log-linear interpolation stays within 0.3 %


class Renderer:
    """Renders log intensity at any time (seconds after t0) by warping the canvas texture."""

    def __init__(self, cfg: SceneConfig):
        self.cfg = cfg
        w, h = cfg.width, cfg.height
        v = math.hypot(*cfg.velocity_px_s)
        reach = v * (cfg.oscillation_period_s / math.pi if cfg.oscillation_period_s > 0 else cfg.duration_s)
        margin = int(min(reach, 4 * max(w, h))) + max(w, h) // 2 + 8
        self.canvas_w, self.canvas_h = w + 2 * margin, h + 2 * margin
        # a colour scene (cfg.color_filter set) warps a BGR texture; each sensor pixel sees its own channel
        self.channels = None if cfg.color_filter is None else colour_scene.sensor_channels(cfg.color_filter, h, w)
        make = make_texture if self.channels is None else colour_scene.make_colour_texture
        self.texture = make(cfg.texture, self.canvas_h, self.canvas_w, seed=cfg.seed,
                            intensity_range=cfg.intensity_range, anchor=cfg.texture_anchor, stretch=cfg.texture_stretch)
        self.lamp = None  # canvas weight in [0, 1] of the flickering lamp (None: no lamp)
        if cfg.flicker_hz > 0:
            self.lamp = self._lamp_mask()
            lamp = self.lamp if self.channels is None else self.lamp[..., None]  # a white lamp
            self.texture = (self.texture * (1 - lamp) + cfg.flicker_level * lamp).astype(np.float32)
        self.log_texture = np.log(self.texture)

    def _lamp_mask(self) -> np.ndarray:
        """A soft-edged disk on the canvas, placed where flicker_region says it is at t = 0."""
        cfg = self.cfg
        fx, fy, fr = cfg.flicker_region
        m = self.matrix(0.0)
        px, py = fx * (cfg.width - 1), fy * (cfg.height - 1)
        cx, cy = m[0, 0] * px + m[0, 1] * py + m[0, 2], m[1, 0] * px + m[1, 1] * py + m[1, 2]
        yy, xx = np.mgrid[0:self.canvas_h, 0:self.canvas_w].astype(np.float32)
        dist = np.hypot(xx - cx, yy - cy)
        return np.clip(fr * cfg.height - dist + 0.5, 0.0, 1.0).astype(np.float32)

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

    def _warp(self, img: np.ndarray, t_s: float) -> np.ndarray:
        return cv2.warpAffine(img, self.matrix(t_s), (self.cfg.width, self.cfg.height),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT_101)

    def lamp_gain(self, t_s: float) -> float:
        """log of the lamp's intensity factor at t_s (0 without a lamp)."""
        cfg = self.cfg
        if self.lamp is None:
            return 0.0
        return math.log1p(cfg.flicker_depth * math.sin(2 * math.pi * cfg.flicker_hz * t_s))

    def log_frame(self, t_s: float) -> np.ndarray:
        """(H, W) log intensity each sensor pixel sees (its own channel's in a colour scene)."""
        out = self._warp(self.log_texture, t_s)  # float32: per-step work is float32, accumulators float64
        if self.channels is not None:
            out = colour_scene.mosaic_log(out, self.channels)
        if self.lamp is not None:
            out += np.float32(self.lamp_gain(t_s)) * self._warp(self.lamp, t_s)
        return out

    def log_frame_bgr(self, t_s: float) -> np.ndarray:
        """(H, W, 3) BGR log intensity of a colour scene at t_s: every channel at every pixel."""
        out = self._warp(self.log_texture, t_s)
        if self.lamp is not None:
            out += np.float32(self.lamp_gain(t_s)) * self._warp(self.lamp, t_s)[..., None]
        return out

    def lamp_image(self, t_s: float) -> np.ndarray | None:
        """The lamp's weight in the output image at t_s, or None without a lamp."""
        return None if self.lamp is None else self._warp(self.lamp, t_s)

    def max_speed_px_s(self) -> float:
        cfg = self.cfg
        r = math.hypot(cfg.width, cfg.height) / 2
        growth = abs(cfg.zoom_per_s) * cfg.duration_s
        zoom = abs(cfg.zoom_per_s) * r * math.exp(growth) if growth < 700 else math.inf  # exp() overflows past ~709
        return math.hypot(*cfg.velocity_px_s) + abs(math.radians(cfg.rotation_deg_s)) * r + zoom


def choose_step_us(cfg: SceneConfig, speed_px_s: float) -> int:
    """The render grid: the largest divisor of the APS timing that keeps motion per step <= max_step_px
    (and samples a flickering lamp finely enough), at most 1 ms."""
    g = math.gcd(math.gcd(cfg.exposure_us, cfg.frame_interval_us), max(cfg.first_exposure_us, 0) or cfg.exposure_us)
    if cfg.step_us:
        if g % cfg.step_us:
            raise ValueError(f"step_us={cfg.step_us} must divide exposure, frame interval and first exposure ({g} µs)")
        return cfg.step_us
    want = 1000.0 if speed_px_s <= 0 else min(1000.0, cfg.max_step_px / speed_px_s * 1e6)
    if want < 1:  # a 1 µs grid would still move more than max_step_px per step; and millions of steps per second
        raise ValueError(f"the scene moves up to {speed_px_s:.3g} px/s, faster than the simulator renders "
                         f"({cfg.max_step_px * 1e6:.3g} px/s: {cfg.max_step_px} px per µs step); lower the velocity, "
                         f"rotation or zoom (or the duration, a zoom grows with it)")
    if cfg.flicker_hz > 0:
        want = min(want, 1e6 / (cfg.flicker_hz * FLICKER_STEPS_PER_PERIOD))
        if want < 1:
            raise ValueError(f"flicker_hz {cfg.flicker_hz:g} is faster than the simulator's 1 µs render grid "
                             f"samples ({FLICKER_STEPS_PER_PERIOD} steps per period)")
    best = 1
    for d in range(1, int(math.isqrt(g)) + 1):
        if g % d == 0:
            for cand in (d, g // d):
                if cand <= want and cand > best:
                    best = cand
    return best
