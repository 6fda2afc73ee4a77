"""numba kernels of the sub-threshold residual estimate between a pixel's events (see edi_live.edi.residual):
the per-event link to the same pixel's next event, each pixel's last and next event as the events stream in,
and the residual at the active pixels, rendered on top of a log image through the bucket tables.

Private to edi_live.edi (see edi_live.edi.residual and its numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _clip, _u8


@njit(cache=True, nogil=True)
def link_next(x, y, width, height, mask, use_mask, snap, nxt, first, before):
    """nxt[i] = the next event of event i's pixel (-1: none), first[q] = pixel q's first event (-1: none),
    before[q] = pixel q's last event before index `snap` (-1: none); events off the sensor or at masked pixels are
    left out (nxt -1, never linked)."""
    last = np.full(width * height, -1, np.int64)
    for i in range(x.size):
        if i == snap:
            before[:] = last
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
    if snap >= x.size:
        before[:] = last


@njit(cache=True, nogil=True)
def start_from(before, tt, p, nxt, c_on, c_off, never, last_t, last_c, next_t, next_c):
    """Each pixel's last and next event as they stand after the events before[q] (-1: none)."""
    for q in range(before.size):
        a = before[q]
        if a < 0:
            last_t[q] = 0
            last_c[q] = 0.0
            next_t[q] = never
            next_c[q] = 0.0
            continue
        _take(q, a, tt, p, nxt, c_on, c_off, never, last_t, last_c, next_t, next_c)


@njit(cache=True, nogil=True, inline="always")
def _take(q, i, tt, p, nxt, c_on, c_off, never, last_t, last_c, next_t, next_c):
    """Pixel q's last event becomes event i (time, signed threshold), its next event i's successor."""
    last_t[q] = tt[i]
    last_c[q] = c_on if p[i] else -c_off
    b = nxt[i]
    if b >= 0:
        next_t[q] = tt[b]
        next_c[q] = c_on if p[b] else -c_off
    else:
        next_t[q] = never
        next_c[q] = 0.0


@njit(cache=True, nogil=True)
def advance(x, y, p, tt, nxt, width, height, mask, use_mask, start, end, c_on, c_off, never, last_t, last_c,
            next_t, next_c):
    """For the events start <= i < end: their pixel's last event (time, signed threshold) becomes i and its next
    event i's successor (time `never` and threshold 0 when there is none)."""
    for i in range(start, end):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        _take(q, i, tt, p, nxt, c_on, c_off, never, last_t, last_c, next_t, next_c)


@njit(cache=True, nogil=True)
def residual_at(t, active, last_t, last_c, next_t, next_c, table_a, table_b, a_unknown, seen_from, seen_to, out):
    """out[q] = the residual estimate at time t for the active pixels q (the others untouched), as if only the
    events with seen_from <= t <= seen_to had been seen (last_c 0: no last event)."""
    nb = table_a.size
    for k in range(active.size):
        q = active[k]
        ta = last_t[q]
        ca = last_c[q]
        if ca == 0.0 or ta < seen_from:
            out[q] = 0.0
            continue
        tb = next_t[q]
        if tb > seen_to:
            out[q] = a_unknown * ca
            continue
        span = tb - ta
        i = min(max(int((t - ta) * (nb / span)), 0), nb - 1) if span > 0 else nb - 1
        out[q] = table_a[i] * ca + table_b[i] * next_c[q]


@njit(cache=True, nogil=True)
def render_with(flat, res, active, lo, hi, disp, v0, scale, bucket_u8, bucket_thr):
    """disp[q] = the uint8 image of flat[q] + res[q] at the active pixels."""
    for k in range(active.size):
        q = active[k]
        v = flat[q] + res[q]
        v = _clip(v, lo, hi)
        disp[q] = _u8(v, v0, scale, bucket_u8, bucket_thr)


@njit(cache=True, nogil=True)
def residual_paint(t, active, last_t, last_c, next_t, next_c, table_a, table_b, a_unknown, seen_from, seen_to,
                   out, flat, lo, hi, disp, v0, scale, bucket_u8, bucket_thr):
    """residual_at and render_with in one pass over the active pixels (what a fused frame needs)."""
    nb = table_a.size
    for k in range(active.size):
        q = active[k]
        ta = last_t[q]
        ca = last_c[q]
        r = np.float32(0.0)
        if ca != 0.0 and ta >= seen_from:
            tb = next_t[q]
            if tb > seen_to:
                r = a_unknown * ca
            else:
                span = tb - ta
                i = min(max(int((t - ta) * (nb / span)), 0), nb - 1) if span > 0 else nb - 1
                r = table_a[i] * ca + table_b[i] * next_c[q]
        out[q] = r
        v = flat[q] + r
        v = _clip(v, lo, hi)
        disp[q] = _u8(v, v0, scale, bucket_u8, bucket_thr)
