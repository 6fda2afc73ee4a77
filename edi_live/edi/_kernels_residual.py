"""numba kernels of the sub-threshold residual estimate between a pixel's events (see edi_live.edi.residual):
the per-event link to the same pixel's next event, the per-pixel last event as the events stream in, and the
residual (optionally rendered on top of a log image through the bucket tables).

Private to edi_live.edi (see edi_live.edi.residual and its numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _u8


@njit(cache=True, nogil=True)
def link_next(x, y, width, height, mask, use_mask, nxt, first):
    """nxt[i] = the next event of event i's pixel (-1: none), first[q] = pixel q's first event (-1: none);
    events off the sensor or at masked pixels are left out (nxt -1, never linked)."""
    last = np.full(width * height, -1, np.int64)
    for i in range(x.size):
        nxt[i] = -1
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        j = last[q]
        if j >= 0:
            nxt[j] = i
        else:
            first[q] = i
        last[q] = i


@njit(cache=True, nogil=True)
def advance(x, y, width, height, mask, use_mask, start, end, last):
    """last[q] = i for the events start <= i < end (the newest event of each pixel so far)."""
    for i in range(start, end):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        last[q] = i


@njit(cache=True, nogil=True)
def residual_at(t, tt, p, nxt, last, active, c_on, c_off, table_a, table_b, a_unknown, seen_from, seen_to, out):
    """out[q] = the residual estimate at time t for the active pixels q (the others untouched), as if only the
    events with seen_from <= t <= seen_to had been seen."""
    nb = table_a.size
    for k in range(active.size):
        q = active[k]
        a = last[q]
        if a < 0 or tt[a] < seen_from:
            out[q] = 0.0
            continue
        ca = c_on if p[a] else -c_off
        b = nxt[a]
        if b < 0 or tt[b] > seen_to:
            out[q] = a_unknown * ca
            continue
        cb = c_on if p[b] else -c_off
        span = tt[b] - tt[a]
        x = (t - tt[a]) / span if span > 0 else 1.0
        i = min(max(int(x * nb), 0), nb - 1)
        out[q] = table_a[i] * ca + table_b[i] * cb


@njit(cache=True, nogil=True)
def render_with(flat, res, active, lo, hi, disp, v0, scale, bucket_u8, bucket_thr):
    """disp[q] = the uint8 image of flat[q] + res[q] at the active pixels."""
    for k in range(active.size):
        q = active[k]
        v = flat[q] + res[q]
        if v < lo:
            v = lo
        elif v > hi:
            v = hi
        disp[q] = _u8(v, v0, scale, bucket_u8, bucket_thr)
