"""numba kernels of the level-table math: the O(events + pixels) table build (counting sort by pixel, one pass),
the per-pixel divisor evaluation, and the consistency cost of the c estimator built on the same sums.

Private to edi_live.edi: call them through the public functions there, which also hold the numpy references that
these must match (the tests compare both).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

@njit(cache=True, nogil=True)
def build_table(t, x, y, p, width, height, mask, use_mask, ts, te, f, want_segments, count_all, use_count_all):
    """Events come as (strided) field views of one time-ordered slice; out-of-range and masked pixels are
    skipped here, so no temporary index arrays are needed. count_all (if used) gets every in-range event."""
    npix = width * height
    count = np.zeros(npix + 1, dtype=np.int64)
    for i in range(t.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_count_all:
            count_all[q] += 1
        if use_mask and mask[q]:
            continue
        count[q + 1] += 1
    n_act = 0
    for k in range(1, npix + 1):
        if count[k] > 0:
            n_act += 1
        count[k] += count[k - 1]
    n = count[npix]
    # counting sort: events grouped by pixel, time order kept inside each group (sequential reads)
    fill = count[:-1].copy()
    st = np.empty(n, dtype=np.int64)
    sp = np.empty(n, dtype=np.uint8)
    for i in range(t.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        k = fill[q]
        st[k] = t[i]
        sp[k] = p[i]
        fill[q] = k + 1
    n_seg = n + n_act if want_segments else 0
    pixels = np.empty(n_act, dtype=np.int64)
    seg_start = np.zeros(n_act + 1, dtype=np.int64)
    seg_on = np.empty(n_seg, dtype=np.int32)
    seg_off = np.empty(n_seg, dtype=np.int32)
    seg_frac = np.empty(n_seg, dtype=np.float64)
    lvl_start = np.empty(n_act + 1, dtype=np.int64)
    lvl_min = np.empty(n_act, dtype=np.int32)
    lvl_frac = np.zeros(n + n_act, dtype=np.float64)  # a pixel with k events spans at most k + 1 levels
    inv_t = 1.0 / float(te - ts)
    g = 0
    s = 0
    base = 0
    for q in range(npix):
        a = count[q]
        b = count[q + 1]
        if a == b:
            continue
        # pass 1: net level range counted from ts, and the counts reached at f
        on0 = np.int64(0)
        off0 = np.int64(0)
        lo = 0
        hi = 0
        j_on = 0
        j_off = 0
        for k in range(a, b):
            on0 += sp[k]  # branch-free: polarities are unpredictable
            off0 += 1 - sp[k]
            if st[k] <= f:
                j_on = on0
                j_off = off0
            net = on0 - off0
            lo = min(lo, net)
            hi = max(hi, net)
        pixels[g] = q
        lvl_start[g] = base
        lvl_min[g] = lo - (j_on - j_off)
        # pass 2: dwell per level (and per ON/OFF state when asked)
        net = 0
        frac = (st[a] - ts) * inv_t
        lvl_frac[base - lo] += frac
        if want_segments:
            seg_start[g] = s
            seg_on[s] = -j_on
            seg_off[s] = -j_off
            seg_frac[s] = frac
            s += 1
            on0 = 0
            off0 = 0
        for k in range(a, b):
            net += 2 * np.int64(sp[k]) - 1
            nxt = te if k + 1 == b else st[k + 1]
            frac = (nxt - st[k]) * inv_t
            lvl_frac[base + net - lo] += frac
            if want_segments:
                on0 += sp[k]
                off0 += 1 - sp[k]
                seg_on[s] = on0 - j_on
                seg_off[s] = off0 - j_off
                seg_frac[s] = frac
                s += 1
        base += hi - lo + 1
        g += 1
    seg_start[n_act] = s
    lvl_start[n_act] = base
    return pixels, seg_start, seg_on, seg_off, seg_frac, lvl_start, lvl_min, lvl_frac[:base], n


@njit(cache=True, nogil=True, inline="always")  # numba IR inlining: a plain call costs speed here
def _exp_table(c, n):
    """exp(c * j) for j in range(n): the per-level weights, so the sums below need no exp per level."""
    ztab = np.empty(n, dtype=np.float64)
    for j in range(n):
        ztab[j] = math.exp(c * j)
    return ztab


@njit(cache=True, nogil=True, inline="always")  # numba IR inlining: a plain call costs speed here
def _level_sum(frac, a, b, ztab):
    """sum_k frac[k] * exp(c * (k - a)) over one pixel's levels [a, b), the weights read from ztab."""
    acc = 0.0
    for k in range(a, b):
        acc += frac[k] * ztab[k - a]
    return acc


@njit(cache=True, nogil=True, inline="always")  # numba IR inlining: a plain call costs speed here
def _log_level_sum_wide(frac, a, b, c, lvl_min):
    """c * lvl_min + log sum_k frac[k] * exp(c * (k - a)) by log-sum-exp over the occupied levels: for level
    ranges too wide for the table (exp(c * (k - a)) would overflow)."""
    m = -math.inf
    for k in range(a, b):
        if frac[k] > 0.0 and c * (k - a) > m:
            m = c * (k - a)
    acc = 0.0
    for k in range(a, b):
        if frac[k] > 0.0:
            acc += frac[k] * math.exp(c * (k - a) - m)
    return c * lvl_min + m + math.log(acc)


@njit(cache=True, nogil=True)
def log_divisor_levels(lvl_start, lvl_min, lvl_frac, c, cap):
    n_act = lvl_min.size
    out = np.empty(n_act, dtype=np.float64)
    wmax = 1
    for r in range(n_act):
        w = lvl_start[r + 1] - lvl_start[r]
        if w > wmax:
            wmax = w
    if wmax > cap:
        wmax = cap
    ztab = _exp_table(c, wmax)
    for r in range(n_act):
        a = lvl_start[r]
        b = lvl_start[r + 1]
        if b - a <= cap:
            out[r] = c * lvl_min[r] + math.log(_level_sum(lvl_frac, a, b, ztab))
        else:  # very wide level range
            out[r] = _log_level_sum_wide(lvl_frac, a, b, c, lvl_min[r])
    return out


@njit(cache=True, nogil=True)
def log_divisor_segments(seg_start, seg_on, seg_off, seg_frac, c_on, c_off):
    n_act = seg_start.size - 1
    out = np.empty(n_act, dtype=np.float64)
    for r in range(n_act):
        a = seg_start[r]
        b = seg_start[r + 1]
        m = -math.inf
        for k in range(a, b):
            if seg_frac[k] > 0.0:
                v = c_on * seg_on[k] - c_off * seg_off[k]
                if v > m:
                    m = v
        acc = 0.0
        for k in range(a, b):
            if seg_frac[k] > 0.0:
                acc += seg_frac[k] * math.exp(c_on * seg_on[k] - c_off * seg_off[k] - m)
        out[r] = m + math.log(acc)
    return out



@njit(cache=True, nogil=True)
def _divisor_sums(start, lvl_min, frac, rows, c, ztab, cap, sign, ratio, offset):
    """For each sub-table row: D = exp(c*lvl_min) * sum_j frac_j * ztab[j]; multiplies ratio[row] by the sum
    (sign +1) or divides by it (sign -1) and adds sign * c * lvl_min to offset[row]. Rows wider than `cap` get
    their log D (log-sum-exp) added to offset directly."""
    for r in range(rows.size):
        a = start[r]
        b = start[r + 1]
        i = rows[r]
        if b - a <= cap:
            acc = _level_sum(frac, a, b, ztab)
            if sign > 0:
                ratio[i] *= acc
            else:
                ratio[i] /= acc
            offset[i] += sign * c * lvl_min[r]
        else:
            offset[i] += sign * _log_level_sum_wide(frac, a, b, c, lvl_min[r])


@njit(cache=True, nogil=True)
def consistency_cost(c, dlog_b, net, weight, delta2, start_p, min_p, frac_p, row_p, start_c, min_c, frac_c, row_c,
                     cap, terms):
    """sum_i weight_i * sqrt(delta2 + r_i^2), r = dlog_b - (c*net + log D_cur - log D_prev), for c_on == c_off.
    `terms`: empty, or an array of dlog_b's size that receives every pixel's term (for the fit test's noise).
    row_* maps each sub-table row to its residual index. One log per residual: log(D_cur / D_prev)."""
    wmax = 1
    for r in range(row_p.size):
        wmax = max(wmax, start_p[r + 1] - start_p[r])
    for r in range(row_c.size):
        wmax = max(wmax, start_c[r + 1] - start_c[r])
    wmax = min(wmax, cap)
    ztab = _exp_table(c, wmax)
    n = net.size
    ratio = np.ones(n, dtype=np.float64)
    offset = c * net
    _divisor_sums(start_p, min_p, frac_p, row_p, c, ztab, cap, -1.0, ratio, offset)
    _divisor_sums(start_c, min_c, frac_c, row_c, c, ztab, cap, 1.0, ratio, offset)
    total = 0.0
    for i in range(n):
        res = dlog_b[i] - (offset[i] + math.log(ratio[i]))
        term = weight[i] * math.sqrt(delta2 + res * res)
        if terms.size:
            terms[i] = term
        total += term
    return total


@njit(cache=True, nogil=True)
def pair_candidates(inf_p, inf_c, bp, bc, b_low, b_high, mask, use_mask, n_on, n_off, pix_p, pix_c):
    """Pixels (ascending) informative in both frames, with both B in [b_low, b_high], not masked, and with
    events between the frames or in either exposure table (pix_p, pix_c): the consistency residual candidates.
    The tests are combined without branches (the loop vectorises), then the few pixels that pass are listed."""
    npix = bp.size
    flag = np.zeros(npix, dtype=np.uint8)
    for r in range(pix_p.size):
        flag[pix_p[r]] = 1
    for r in range(pix_c.size):
        flag[pix_c[r]] = 1
    m = 0
    for q in range(npix):
        f = ((flag[q] | ((n_on[q] + n_off[q]) > 0)) & inf_p[q] & inf_c[q] & (bp[q] >= b_low) & (bp[q] <= b_high)
             & (bc[q] >= b_low) & (bc[q] <= b_high))
        if use_mask:
            f = f & (mask[q] == 0)
        flag[q] = f
        m += f
    out = np.empty(m, dtype=np.int64)
    k = 0
    for q in range(npix):
        if flag[q]:
            out[k] = q
            k += 1
    return out


@njit(cache=True, nogil=True)
def ragged_take(start, rows):
    """(entry indices, new offsets) of the ragged rows `rows` of a table with offsets `start`, in row order."""
    new_start = np.zeros(rows.size + 1, dtype=np.int64)
    for r in range(rows.size):
        new_start[r + 1] = new_start[r] + start[rows[r] + 1] - start[rows[r]]
    idx = np.empty(new_start[rows.size], dtype=np.int64)
    k = 0
    for r in range(rows.size):
        for j in range(start[rows[r]], start[rows[r] + 1]):
            idx[k] = j
            k += 1
    return idx, new_start


@njit(cache=True, nogil=True)
def rows_of(table_pixels, lvl_start, pixels, spread):
    """(rows, at): the table rows holding those of `pixels` (ascending) that are active, and their positions in
    `pixels` (both merged in one pass: both lists ascend). Adds each such pixel's level count - 1 to spread[at].
    A pixel listed twice matches its row twice, as the numpy path does (hence one slot per pixel)."""
    rows = np.empty(pixels.size, dtype=np.int64)
    at = np.empty(rows.size, dtype=np.int64)
    m = 0
    r = 0
    for i in range(pixels.size):
        q = pixels[i]
        while r < table_pixels.size and table_pixels[r] < q:
            r += 1
        if r == table_pixels.size:
            break
        if table_pixels[r] == q:
            rows[m] = r
            at[m] = i
            spread[i] += lvl_start[r + 1] - lvl_start[r] - 1
            m += 1
    return rows[:m], at[:m]
