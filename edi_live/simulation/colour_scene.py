"""Colour scenes: what a colour DAVIS346 (a Bayer filter over the APS and DVS pixels) sees of an RGB scene.

A scene is colour when `SceneConfig.color_filter` names a Bayer pattern (`datatypes.ColorFilter`, e.g. "RGGB",
the DAVIS346 colour default). Then:
- the texture is BGR (`make_colour_texture`): coloured blocks, a colour photograph, or a grey texture tinted
  by a slowly varying colour field;
- each pixel's log intensity is that of its OWN channel (`mosaic_log`), so its events, its APS value and its
  realistic-camera effects (black level, response, read noise, threshold mismatch, refractory period,
  background and hot pixels, the white flickering lamp) all act on the mosaic exactly as on a grey sensor;
- APS frames are raw 2-D mosaics carrying `Frame.color_filter`;
- ground truth is the sharp (H, W, 3) BGR image (all three channels at every pixel), float32 on 0..255 linear.
`color_c_scale` (B, G, R) multiplies each channel's thresholds, for tests of per-channel c estimation.
"""

from __future__ import annotations

import cv2
import numpy as np

from edi_live.datatypes import ColorFilter

DAVIS346_COLOR_FILTER: ColorFilter = "RGGB"  # the DAVIS346 colour's top-left block (BayerBG in OpenCV's naming)
COLOUR_PHOTOGRAPHS = ("astronaut", "coffee", "chelsea", "rocket")


def _colour_blocks(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """Random saturated rectangles and disks on a grey ground: sharp luminance AND colour edges."""
    img = np.full((h, w, 3), 0.5, np.float32)
    for _ in range(int(h * w / 900) + 10):
        colour = tuple(float(v) for v in rng.uniform(0.0, 1.0, 3))
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        size = int(rng.integers(6, 40))
        if rng.random() < 0.6:
            cv2.rectangle(img, (cx - size, cy - size // 2), (cx + size, cy + size // 2), colour, -1)
        else:
            cv2.circle(img, (cx, cy), size // 2, colour, -1)
    small = rng.random((max(2, h // 6 + 2), max(2, w // 6 + 2))).astype(np.float32)
    img += 0.15 * (cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC) - 0.5)[..., None]
    return img


def _tint(grey: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A grey texture times a smooth per-channel gain field (cells ~48 px): correlated channels like a photo."""
    h, w = grey.shape
    small = rng.uniform(0.35, 1.0, (max(2, h // 48 + 2), max(2, w // 48 + 2), 3)).astype(np.float32)
    return grey[..., None] * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def make_colour_texture(name: str, height: int, width: int, *, seed: int = 0,
                        intensity_range: tuple[float, float] = (0.05, 0.95), anchor: str = "top-left",
                        stretch: tuple[float, float] = (0.0, 100.0)) -> np.ndarray:
    """A float32 (height, width, 3) BGR texture with linear intensities in `intensity_range` (strictly positive).

    "blocks": coloured blocks; a colour scikit-image photograph (COLOUR_PHOTOGRAPHS): itself, enlarged and
    cropped as the grey textures are; any other grey texture name: tinted by a smooth random colour field.
    """
    from edi_live.simulation.texture import make_texture

    rng = np.random.default_rng([seed, 11])
    if name == "blocks":
        img = cv2.GaussianBlur(_colour_blocks(height, width, np.random.default_rng(seed)), (0, 0), 0.8)
    elif name in COLOUR_PHOTOGRAPHS:
        from skimage import data  # test extra, as for the grey photographs

        src = cv2.cvtColor(getattr(data, name)(), cv2.COLOR_RGB2BGR).astype(np.float32) / 255.0
        scale = max(height / src.shape[0], width / src.shape[1], 1.0)
        if scale > 1.0:
            src = cv2.resize(src, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        y0, x0 = ((src.shape[0] - height) // 2, (src.shape[1] - width) // 2) if anchor == "centre" else (0, 0)
        img = cv2.GaussianBlur(np.ascontiguousarray(src[y0:y0 + height, x0:x0 + width]), (0, 0), 0.8)
    else:
        grey = make_texture(name, height, width, seed=seed, intensity_range=(0.0, 1.0), anchor=anchor,
                            stretch=stretch)
        img = _tint(grey, rng)
    lo_p, hi_p = np.percentile(img, stretch) if tuple(stretch) != (0.0, 100.0) else (img.min(), img.max())
    img = np.clip((img - float(lo_p)) / max(float(hi_p - lo_p), 1e-6), 0.0, 1.0)
    lo, hi = intensity_range
    return (lo + (hi - lo) * img).astype(np.float32)


def mosaic_log(log_bgr: np.ndarray, channels: np.ndarray) -> np.ndarray:
    """(H, W) log intensity each pixel sees through its filter, from the (H, W, 3) BGR log image."""
    return np.take_along_axis(log_bgr, channels[..., None].astype(np.intp), axis=2)[..., 0]


def sensor_channels(pattern: str, height: int, width: int) -> np.ndarray:
    """(H, W) int8 BGR channel index (0 = B, 1 = G, 2 = R) of each sensor pixel: the pattern names the top-left
    2x2 block row by row. The simulator's own reading of the name (it is the ground truth, so it does not borrow
    edi_live.colour's; a test checks that the two agree)."""
    if pattern not in ("RGGB", "GRBG", "GBRG", "BGGR"):
        raise ValueError(f"unknown Bayer pattern {pattern!r} (known: RGGB, GRBG, GBRG, BGGR)")
    block = np.array(["BGR".index(letter) for letter in pattern], np.int8).reshape(2, 2)
    return np.tile(block, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def scale_thresholds(con: np.ndarray, coff: np.ndarray, channels: np.ndarray,
                     scale: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel thresholds (flat) times their channel's factor of `scale` (B, G, R)."""
    factor = np.asarray(scale, np.float32)[channels.ravel()]
    return (con * factor).astype(np.float32), (coff * factor).astype(np.float32)
