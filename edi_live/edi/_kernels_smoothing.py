"""numba kernel of edi_live.edi.smoothing: the 3x3 median of per-pixel values at the active pixels (the frame finish
that shows it is _kernels_stream.finish_frame_u8).

Private to edi_live.edi (see smoothing.py for the contract and the numpy reference).
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _median9(p0, p1, p2, p3, p4, p5, p6, p7, p8):
    """The middle of 9 values by a fixed network of 19 compare-exchanges (min/max, no branch on the data; an
    insertion sort's unpredictable branches cost ~50 ns a pixel). Inlined into numba IR, it is compiled with its
    caller's flags: fastmath in median_dense, not in median_at's per-pixel loop. Inputs are finite (log D
    always is); with a NaN the result depends on where it sits."""
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
def median_at(pixels, values, width, height, step, grid, dense, out):
    """out[r] = the median of values over the 3x3 neighbours `step` apart of pixels[r] (0 where a neighbour is not
    in `pixels`; a neighbour off the sensor is the pixel itself). `grid` (width * height) must come zeroed and is
    left zeroed; `dense` (width * height, or empty) as for _medians. Values are held in the grid's dtype."""
    for r in range(pixels.size):
        grid[pixels[r]] = values[r]
    _medians(pixels, width, height, step, grid, dense, out)
    for r in range(pixels.size):
        grid[pixels[r]] = 0.0


@njit(cache=True, nogil=True)
def smoothed_pair(pixels, log_d, delta, width, height, step, grid, dense, shown, jump):
    """edi.smoothed_divisor in one call, in the grid's dtype (float32: what the frame finish reads): shown = the
    median of log_d, jump = shown - the median of (log_d - delta). grid zeroed in and out."""
    for r in range(pixels.size):
        grid[pixels[r]] = log_d[r]
    _medians(pixels, width, height, step, grid, dense, shown)
    for r in range(pixels.size):
        grid[pixels[r]] = log_d[r] - delta[r]
    _medians(pixels, width, height, step, grid, dense, jump)
    for r in range(pixels.size):
        jump[r] = shown[r] - jump[r]
        grid[pixels[r]] = 0.0


@njit(cache=True, nogil=True)
def _medians(pixels, width, height, step, grid, dense, out):
    """out[r] = the median over the 3x3 neighbours `step` apart of pixels[r] in `grid`. With step 1 and more than a
    sixth of the pixels active, from one dense pass into `dense` (width * height, or empty: never dense); the same
    values either way."""
    if step == 1 and dense.size == grid.size and pixels.size * 6 > grid.size:
        median_dense(grid, width, height, dense)
        for r in range(pixels.size):
            out[r] = dense[pixels[r]]
        return
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


@njit(cache=True, nogil=True, fastmath=True)
def median_dense(grid, width, height, out):
    """out[q] = the median of grid over the 3x3 neighbours of every pixel q (step 1; a neighbour off the sensor is the
    pixel itself). Inside the border, row by row on contiguous row views with the same network: LLVM vectorises it
    (fastmath lets it use vector min/max; the values are finite and min/max are exact either way), ~1 ns a pixel
    against ~6-7 for median_at's gathers, which pays once more than about a sixth of the pixels are active."""
    for y in range(height):
        up = (y - 1 if y > 0 else y) * width
        mid = y * width
        dn = (y + 1 if y + 1 < height else y) * width
        for x in (0, width - 1):
            lf = x - 1 if x > 0 else x
            rt = x + 1 if x + 1 < width else x
            out[mid + x] = _median9(grid[up + lf], grid[up + x], grid[up + rt], grid[mid + lf], grid[mid + x],
                                    grid[mid + rt], grid[dn + lf], grid[dn + x], grid[dn + rt])
        a = grid[up:up + width]
        b = grid[mid:mid + width]
        c = grid[dn:dn + width]
        o = out[mid:mid + width]
        for x in range(1, width - 1):
            o[x] = _median9(a[x - 1], a[x], a[x + 1], b[x - 1], b[x], b[x + 1], c[x - 1], c[x], c[x + 1])
