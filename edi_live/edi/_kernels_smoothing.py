"""numba kernels of edi_live.edi.smoothing: the 3x3 median of per-pixel values at the active pixels, and the frame
finish that shows the smoothed divisor while the reference keeps each pixel's own.

Private to edi_live.edi (see smoothing.py for the contract and the numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _clip, _u8, fill_from_tables


@njit(cache=True, nogil=True, inline="always")
def _median9(p0, p1, p2, p3, p4, p5, p6, p7, p8):
    """The middle of 9 values by a fixed network of 19 compare-exchanges (min/max, no branch on the data; an
    insertion sort's unpredictable branches cost ~50 ns a pixel)."""
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p0, p1 = min(p0, p1), max(p0, p1)
    p3, p4 = min(p3, p4), max(p3, p4)
    p6, p7 = min(p6, p7), max(p6, p7)
    p1, p2 = min(p1, p2), max(p1, p2)
    p4, p5 = min(p4, p5), max(p4, p5)
    p7, p8 = min(p7, p8), max(p7, p8)
    p3 = max(p0, p3)
    p5 = min(p5, p8)
    p4, p7 = min(p4, p7), max(p4, p7)
    p6 = max(p3, p6)
    p4 = max(p1, p4)
    p2 = min(p2, p5)
    p4 = min(p4, p7)
    p4, p2 = min(p4, p2), max(p4, p2)
    p4 = max(p6, p4)
    return min(p4, p2)


@njit(cache=True, nogil=True)
def median_at(pixels, values, width, height, step, grid, out):
    """out[r] = the median of values over the 3x3 neighbours `step` apart of pixels[r] (0 where a neighbour is not
    in `pixels`; a neighbour off the sensor is the pixel itself). `grid` (width * height float64) must come zeroed
    and is left zeroed."""
    for r in range(pixels.size):
        grid[pixels[r]] = values[r]
    row = step * width
    for r in range(pixels.size):
        q = pixels[r]
        y = q // width
        x = q - y * width
        up = q - row if y >= step else q
        dn = q + row if y + step < height else q
        lf = step if x >= step else 0
        rt = step if x + step < width else 0
        out[r] = _median9(grid[up - lf], grid[up], grid[up + rt], grid[q - lf], grid[q], grid[q + rt],
                          grid[dn - lf], grid[dn], grid[dn + rt])
    for r in range(pixels.size):
        grid[pixels[r]] = 0.0


@njit(cache=True, nogil=True)
def finish_frame_shown_u8(img, sat, dark, lut_log, lut_u8, pixels, log_d, shown_d, shown_jump, lo, hi, log_ref,
                          deblurred, log_lat, display, v0, scale, bucket_u8, bucket_thr):
    """_kernels_stream.finish_frame_u8 with the image shown apart from the reference: log_ref from each pixel's own
    log D (`log_d`), the deblurred image from `shown_d`, the latent log image at te from that plus `shown_jump`."""
    fill_from_tables(img, lut_log, lut_u8, log_ref, deblurred, log_lat, display)
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
