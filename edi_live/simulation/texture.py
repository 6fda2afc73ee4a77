"""Textures for the simulated scene: procedural ones (numpy/cv2 only) and scikit-image photographs.

Owns `make_texture`: a strictly positive, band-limited linear-intensity image that the motion model warps.
"""

from __future__ import annotations

import cv2
import numpy as np

PROCEDURAL_TEXTURES = ("blocks", "noise", "stripes")
SKIMAGE_TEXTURES = ("camera", "astronaut", "brick", "grass", "gravel", "moon", "coins", "text")


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
                 intensity_range: tuple[float, float] = (0.05, 0.95), anchor: str = "top-left",
                 stretch: tuple[float, float] = (0.0, 100.0)) -> np.ndarray:
    """A float32 (height, width) texture with linear intensities in `intensity_range` (strictly positive).

    Procedural names ("blocks", "noise", "stripes") use numpy only; scikit-image names ("camera",
    "astronaut", "brick", "grass", ...) are enlarged to cover the canvas and cropped at its top-left corner
    or, with anchor="centre", around the photograph's centre (small canvases: the subject). A light blur (optics) keeps the
    texture band-limited so sub-pixel warps and log-linear interpolation between render steps are accurate.
    `stretch` (percentiles) maps the texture's range onto `intensity_range`, clipping what lies outside.
    """
    rng = np.random.default_rng(seed)
    bounds = None  # percentiles of the whole photograph, so the crop does not change the stretch
    if name in PROCEDURAL_TEXTURES:
        img = _procedural(name, height, width, rng)
    elif name in SKIMAGE_TEXTURES:
        src = _skimage_texture(name)
        scale = max(height / src.shape[0], width / src.shape[1], 1.0)
        if scale > 1.0:
            src = cv2.resize(src, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        y0, x0 = ((src.shape[0] - height) // 2, (src.shape[1] - width) // 2) if anchor == "centre" else (0, 0)
        img = src[y0:y0 + height, x0:x0 + width]
        if tuple(stretch) != (0.0, 100.0):
            bounds = np.percentile(cv2.GaussianBlur(src, (0, 0), 0.8), stretch)
    else:
        raise ValueError(f"unknown texture {name!r}; choose from {PROCEDURAL_TEXTURES + SKIMAGE_TEXTURES}")
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    lo, hi = intensity_range
    if tuple(stretch) == (0.0, 100.0):
        mn, mx = float(img.min()), float(img.max())
        img = (img - mn) / max(mx - mn, 1e-6)
    else:
        lo_hi = np.percentile(img, stretch) if bounds is None else bounds
        mn, mx = float(lo_hi[0]), float(lo_hi[1])
        img = np.clip((img - mn) / max(mx - mn, 1e-6), 0.0, 1.0)
    return (lo + (hi - lo) * img).astype(np.float32)
