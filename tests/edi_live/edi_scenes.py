"""A small ESIM-style scene generator for the EDI tests (a fixture, not the product simulator in tools/).

A texture translates at constant velocity. Events come from log-intensity threshold crossings with linearly
interpolated timestamps (ESIM); each APS frame is the mean of LINEAR intensity over its exposure; the ground
truth is the sharp frame at mid-exposure. Intensities are on the 8-bit scale (0..255).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from edi_live.datatypes import EVENT_DTYPE, Frame


def texture(name: str) -> np.ndarray:
    """A float32 texture in [0, 1], at least 256x256."""
    if name == "noise":  # procedural: smooth random blobs
        rng = np.random.default_rng(7)
        img = cv2.GaussianBlur(rng.random((256, 256)).astype(np.float32), (0, 0), 3.0)
    else:
        import skimage.data

        img = getattr(skimage.data, name)()
        if img.ndim == 3:
            img = img[..., :3].mean(axis=2)
        img = img.astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)  # keeps bilinear sampling from aliasing
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / max(hi - lo, 1e-6), 0.0, 1.0).astype(np.float32)


@dataclass
class Scene:
    width: int
    height: int
    c_on: float
    c_off: float
    events: np.ndarray
    frames: list[Frame]
    sharp_mid: list[np.ndarray]  # ground truth L(f) per frame, float32, 8-bit scale
    render: object  # render(t_us) -> float32 linear intensity (8-bit scale)


def make_scene(tex: str = "brick", *, width: int = 64, height: int = 48, c_on: float = 0.25,
               c_off: float | None = None, velocity_px_per_ms: tuple[float, float] = (0.5, 0.2),
               exposure_us: int = 8000, period_us: int = 20000, n_frames: int = 3, sigma_c: float = 0.0,
               dt_us: int = 25, lo: float = 0.08, hi: float = 0.9, noise_hz: float = 0.0, hot_pixels: int = 0,
               hot_rate_hz: float = 2000.0, seed: int = 0) -> Scene:
    c_off = c_on if c_off is None else c_off
    rng = np.random.default_rng(seed)
    img = texture(tex)
    vx, vy = velocity_px_per_ms
    x0 = img.shape[1] / 2 - width / 2 - vx * n_frames * period_us / 2000.0
    y0 = img.shape[0] / 2 - height / 2 - vy * n_frames * period_us / 2000.0

    def render(t_us: float) -> np.ndarray:
        cx = x0 + vx * t_us / 1000.0 + (width - 1) / 2.0
        cy = y0 + vy * t_us / 1000.0 + (height - 1) / 2.0
        patch = cv2.getRectSubPix(img, (width, height), (float(cx), float(cy)))
        return (255.0 * (lo + (hi - lo) * patch)).astype(np.float32)

    t_end = n_frames * period_us
    times = np.arange(0, t_end + dt_us, dt_us)
    thr_on = np.full((height, width), c_on, np.float64)
    thr_off = np.full((height, width), c_off, np.float64)
    if sigma_c > 0:  # per-pixel threshold mismatch
        thr_on = np.clip(thr_on + rng.normal(0, sigma_c, thr_on.shape), 0.3 * c_on, None)
        thr_off = np.clip(thr_off + rng.normal(0, sigma_c, thr_off.shape), 0.3 * c_off, None)
    prev = np.log(render(0).astype(np.float64))
    # a real pixel's reference level was set at its last event, long before the scene starts: random offset
    ref = prev + rng.uniform(-0.5, 0.5, prev.shape) * np.minimum(thr_on, thr_off)
    chunks = []
    frames_lin = [render(0)]
    for k in range(1, times.size):
        cur_lin = render(times[k])
        frames_lin.append(cur_lin)
        cur = np.log(cur_lin.astype(np.float64))
        span = cur - prev
        for sign, thr in ((1, thr_on), (-1, thr_off)):
            while True:
                nxt = ref + sign * thr
                hit = (cur - nxt) * sign >= 0
                if not hit.any():
                    break
                yy, xx = np.nonzero(hit)
                frac = (nxt[hit] - prev[hit]) / np.where(span[hit] == 0, 1.0, span[hit])
                t = times[k - 1] + np.clip(frac, 0.0, 1.0) * dt_us
                ev = np.zeros(yy.size, EVENT_DTYPE)
                ev["t"] = np.round(t).astype(np.int64)
                ev["x"], ev["y"], ev["p"] = xx, yy, sign > 0
                chunks.append(ev)
                ref[hit] = nxt[hit]
        prev = cur
    if noise_hz > 0:
        n = rng.poisson(noise_hz * width * height * t_end / 1e6)
        chunks.append(_random_events(rng, n, width, height, t_end))
    for _ in range(hot_pixels):
        n = int(hot_rate_hz * t_end / 1e6)
        ev = _random_events(rng, n, 1, 1, t_end)
        ev["x"] = rng.integers(0, width)
        ev["y"] = rng.integers(0, height)
        chunks.append(ev)
    events = np.concatenate(chunks).astype(EVENT_DTYPE) if chunks else np.zeros(0, EVENT_DTYPE)
    events = events[np.argsort(events["t"], kind="stable")]
    stack = np.stack(frames_lin)
    frames, sharp = [], []
    offset = (period_us - exposure_us) // 2 // dt_us * dt_us
    for i in range(n_frames):
        ts = i * period_us + offset
        te = ts + exposure_us
        a, b = ts // dt_us, te // dt_us
        seg = stack[a:b + 1].astype(np.float64)
        blur = (seg[1:-1].sum(0) + 0.5 * (seg[0] + seg[-1])) / (b - a)  # trapezoid over the exposure
        frames.append(Frame(np.clip(np.round(blur), 0, 255).astype(np.uint8), ts, te, seq=i))
        sharp.append(render((ts + te) // 2))
    return Scene(width, height, c_on, c_off, events, frames, sharp, render)


def _random_events(rng, n, width, height, t_end):
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, t_end, n))
    ev["x"] = rng.integers(0, width, n)
    ev["y"] = rng.integers(0, height, n)
    ev["p"] = rng.random(n) < 0.5
    return ev


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.clip(a, 0, 255).astype(np.float64) - b) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))
