"""numba kernels of edi_live.edi.lone: the lone-change test in the 8x8 tiles that events marked (a whole frame is
every tile marked).

Private to edi_live.edi (see lone.py for the contract and the numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit


TILE_SHIFT = 3  # tiles of 8x8 pixels: a frame of 1000 events touches 3-56 % of them on the recordings at hand


@njit(cache=True, nogil=True, inline="always")
def _mark(xi, yi, width, height, tw, tiles):
    """Mark the tiles of pixel (xi, yi)'s 3x3 neighbourhood: those of its four corners cover it (a tile is at least
    3 pixels wide)."""
    x0 = (xi - 1 if xi > 0 else 0) >> TILE_SHIFT
    x1 = (xi + 1 if xi + 1 < width else xi) >> TILE_SHIFT
    y0 = (yi - 1 if yi > 0 else 0) >> TILE_SHIFT
    y1 = (yi + 1 if yi + 1 < height else yi) >> TILE_SHIFT
    tiles[y0 * tw + x0] = 1
    tiles[y0 * tw + x1] = 1
    tiles[y1 * tw + x0] = 1
    tiles[y1 * tw + x1] = 1


@njit(cache=True, nogil=True)
def mark_tiles(x, y, width, height, tw, tiles):
    """tiles[ty * tw + tx] = 1 for every tile that holds a pixel of an event's 3x3 neighbourhood; events off the
    sensor mark nothing."""
    for i in range(x.size):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi < width and yi < height:
            _mark(xi, yi, width, height, tw, tiles)


@njit(cache=True, nogil=True)
def mark_pixel_tiles(pixels, width, height, tw, tiles):
    """mark_tiles for flat pixel indices."""
    for i in range(pixels.size):
        q = np.int64(pixels[i])
        if 0 <= q < width * height:
            _mark(q % width, q // width, width, height, tw, tiles)


@njit(cache=True, nogil=True, fastmath=True)
def _span_signs(log_lat, log_start, width, eps, padded, yy, xa, xb):
    """The signs of pixels xa..xb-1 of row yy (branch-free over contiguous views)."""
    row = yy * width
    d = log_lat[row + xa:row + xb] - log_start[row + xa:row + xb]
    p = padded[(yy + 1) * (width + 2) + 1 + xa:(yy + 1) * (width + 2) + 1 + xb]
    for i in range(xb - xa):
        p[i] = np.int8(d[i] > eps) - np.int8(d[i] < -eps)


@njit(cache=True, nogil=True, fastmath=True)
def _span_verdicts(display, start_display, width, need, padded, yy, xa, xb, shown):
    """shown over pixels xa..xb-1 of row yy: start_display where lone, else display (branch-free over contiguous
    views: 1.1 ns a pixel with the signs, against 7 ns for the same per pixel in a scalar loop per tile)."""
    pw = width + 2
    a = padded[yy * pw + xa:yy * pw + xb + 2]
    b = padded[(yy + 1) * pw + xa:(yy + 1) * pw + xb + 2]
    c = padded[(yy + 2) * pw + xa:(yy + 2) * pw + xb + 2]
    row = yy * width
    disp = display[row + xa:row + xb]
    start = start_display[row + xa:row + xb]
    out = shown[row + xa:row + xb]
    for i in range(xb - xa):
        s = b[i + 1]
        same = (np.int8(a[i] == s) + np.int8(a[i + 1] == s) + np.int8(a[i + 2] == s) + np.int8(b[i] == s)
                + np.int8(b[i + 2] == s) + np.int8(c[i] == s) + np.int8(c[i + 1] == s) + np.int8(c[i + 2] == s))
        m = np.uint8(0) - np.uint8(np.int8(s != 0) & np.int8(same < need))  # 255 where lone
        out[i] = (disp[i] & ~m) | (start[i] & m)


@njit(cache=True, nogil=True)
def update_tiles(log_lat, log_start, display, start_display, width, height, need, eps, padded, tiles, tw, shown):
    """Bring `shown` (what lone_changes_u8 gives) up to date in the marked tiles and unmark them: first every marked
    tile's signs, then their verdicts, which read the signs of neighbouring tiles (marked or not: an unmarked tile's
    pixels and their neighbours did not change since its signs were written). Each tile row is done as one span
    per pixel row from its first marked tile to its last (spans per run of marked tiles cost more: a short span's
    call outweighs its pixels). `padded` keeps the signs between calls; its border stays 0. Returns the tiles
    updated."""
    th = tiles.size // tw
    size = 1 << TILE_SHIFT
    n = 0
    for verdicts in range(2):
        for ty in range(th):
            ya = ty * size
            yb = min(ya + size, height)
            k = ty * tw
            t0 = 0
            while t0 < tw and tiles[k + t0] == 0:
                t0 += 1
            if t0 == tw:
                continue
            t1 = tw
            while tiles[k + t1 - 1] == 0:
                t1 -= 1
            xa = t0 * size
            xb = min(t1 * size, width)
            for yy in range(ya, yb):
                if verdicts:
                    _span_verdicts(display, start_display, width, need, padded, yy, xa, xb, shown)
                else:
                    _span_signs(log_lat, log_start, width, eps, padded, yy, xa, xb)
            if verdicts:
                n += t1 - t0
        if verdicts:
            tiles[:] = 0
    return n
