"""PSNR on the 8-bit APS scale, the measure of the live quality figure (edi_live.quality): plain functions on numpy
arrays. A perfect match reports PSNR_CAP_DB rather than infinity, and no pixel gives None, never NaN.
"""

from __future__ import annotations

import math

import numpy as np

PSNR_CAP_DB = 100.0
_PEAK = 255.0


def _from_sse(sse: float, n: int) -> float | None:
    if n == 0 or not math.isfinite(sse):
        return None
    mse = sse / n
    if mse <= _PEAK**2 * 10 ** (-PSNR_CAP_DB / 10):
        return PSNR_CAP_DB
    return 10.0 * math.log10(_PEAK**2 / mse)


def psnr_pair(prediction: np.ndarray, target: np.ndarray, valid: np.ndarray, n_valid: int,
               active_idx: np.ndarray | None) -> tuple[float | None, float | None]:
    """(PSNR over the valid pixels, PSNR over the active ones), one pass for the squared errors (float32 is
    exact here: differences of 8-bit values and their squares, or of a prediction on the same scale)."""
    sq = np.subtract(prediction, target, dtype=np.float32)
    np.multiply(sq, sq, out=sq)
    np.multiply(sq, valid, out=sq)
    flat = sq.reshape(-1)
    whole = _from_sse(float(flat.sum()), n_valid)  # numpy sums float32 pairwise: relative error ~1e-7
    if active_idx is None or active_idx.size == 0:
        return whole, None
    return whole, _from_sse(float(flat[active_idx].sum()), int(active_idx.size))


def to_8bit_scale(image: np.ndarray, saturation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """APS image -> (B as float32 on the 8-bit scale, informative mask 0 < raw < saturation)."""
    img = np.asarray(image)
    full = 65535.0 if img.dtype == np.uint16 else 255.0
    sat = full if saturation is None else float(saturation)
    b = img.astype(np.float32)
    if full != 255.0:
        b *= np.float32(255.0 / full)
    valid = img > 0
    valid &= img < sat
    if img.dtype.kind == "f":
        valid &= np.isfinite(b)
        b = np.nan_to_num(b, nan=0.0, posinf=255.0, neginf=0.0)
    return b, valid
