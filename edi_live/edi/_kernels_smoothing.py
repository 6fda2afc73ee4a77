"""numba kernels of edi_live.edi.smoothing: the 3x3 median of per-pixel values at the active pixels, and the frame
finish that shows the smoothed divisor while the reference keeps each pixel's own.

Private to edi_live.edi (see smoothing.py for the contract and the numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _clip, _u8


@njit(cache=True, nogil=True, inline="always")
def _median9(buf):
    """The middle of 9 values (insertion sort: 9 values, no allocation)."""
    for i in range(1, 9):
        v = buf[i]
        j = i - 1
        while j >= 0 and buf[j] > v:
            buf[j + 1] = buf[j]
            j -= 1
        buf[j + 1] = v
    return buf[4]


@njit(cache=True, nogil=True)
def median_at(pixels, values, width, height, step, grid, out):
    """out[r] = the median of values over the 3x3 neighbours `step` apart of pixels[r] (0 where a neighbour is not
    in `pixels`; a neighbour off the sensor is the pixel itself). `grid` (width * height float64) must come zeroed
    and is left zeroed."""
    for r in range(pixels.size):
        grid[pixels[r]] = values[r]
    buf = np.empty(9, np.float64)
    for r in range(pixels.size):
        q = pixels[r]
        y = q // width
        x = q - y * width
        k = 0
        for dy in (-step, 0, step):
            yy = y + dy
            if yy < 0 or yy >= height:
                yy = y
            for dx in (-step, 0, step):
                xx = x + dx
                if xx < 0 or xx >= width:
                    xx = x
                buf[k] = grid[yy * width + xx]
                k += 1
        out[r] = _median9(buf)
    for r in range(pixels.size):
        grid[pixels[r]] = 0.0


@njit(cache=True, nogil=True)
def finish_frame_shown_u8(img, sat, dark, lut_log, lut_u8, pixels, log_d, shown_d, shown_jump, lo, hi, log_ref,
                          deblurred, log_lat, display, v0, scale, bucket_u8, bucket_thr):
    """_kernels_stream.finish_frame_u8 with the image shown apart from the reference: log_ref from each pixel's own
    log D (`log_d`), the deblurred image from `shown_d`, the latent log image at te from that plus `shown_jump`."""
    for q in range(img.size):
        i = img[q]
        v = lut_log[i]
        log_ref[q] = v
        log_lat[q] = v
        u = lut_u8[i]
        deblurred[q] = u
        display[q] = u
    for r in range(pixels.size):
        q = pixels[r]
        i = img[q]
        v = lut_log[i]
        s = v
        if i > dark and i < sat:
            log_ref[q] = _clip(v - np.float32(log_d[r]), lo, hi)
            s = _clip(v - np.float32(shown_d[r]), lo, hi)
            deblurred[q] = _u8(s, v0, scale, bucket_u8, bucket_thr)
        w = _clip(s + np.float32(shown_jump[r]), lo, hi)
        log_lat[q] = w
        display[q] = _u8(w, v0, scale, bucket_u8, bucket_thr)
