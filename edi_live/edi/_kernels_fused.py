"""numba kernel of the fused (two-frame) latent image: event propagation with per-pixel ON/OFF steps.

Private to edi_live.edi (see edi_live.edi.fused and its numpy reference).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def propagate_steps(x, y, p, width, height, mask, use_mask, flat, step_on, step_off, lo, hi, disp):
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        v = flat[q] + (step_on[q] if p[i] else step_off[q])
        if v < lo:
            v = lo
        elif v > hi:
            v = hi
        flat[q] = v
        z = math.exp(min(v, 6.0)) + 0.5
        if z > 255.0:
            z = 255.0
        disp[q] = np.uint8(z)


@njit(cache=True, nogil=True)
def pair_sums(x, y, p, width, height, mask, use_mask, c_on, c_off, delta, mass):
    """delta += c_on (ON) / -c_off (OFF) and mass += c_on / c_off per event, flat float32 per pixel."""
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        if p[i]:
            delta[q] += c_on
            mass[q] += c_on
        else:
            delta[q] -= c_off
            mass[q] += c_off
