"""numba kernels for the EDI hot loops; importing this module raises ImportError when numba is missing.

Owns: the O(events + pixels) level-table build (counting sort by pixel, one pass), the per-pixel divisor
evaluation, and per-event latent propagation. `edi_live.edi` holds the numpy equivalents and the contracts;
these must return exactly what the numpy versions return (tests compare both).
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
def propagate(x, y, p, width, height, mask, use_mask, flat, d_on, d_off, lo, hi, disp, use_disp, gain,
              acc_on, acc_off, use_acc):
    applied = 0
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        on = p[i]
        v = flat[q] + (d_on if on else d_off)
        if v < lo:
            v = lo
        elif v > hi:
            v = hi
        flat[q] = v
        if use_disp:
            z = gain * math.exp(min(v, 6.0)) + 0.5
            if z > 255.0:
                z = 255.0
            disp[q] = np.uint8(z)
        if use_acc:
            if on:
                acc_on[q] += 1
            else:
                acc_off[q] += 1
        applied += 1
    return applied


@njit(cache=True, nogil=True)
def count_events(x, y, p, width, height, mask, use_mask, out_on, out_off, sign):
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        on = np.int64(p[i])  # branch-free: polarities are unpredictable (two adds beat a mispredict)
        out_on[q] += sign * on
        out_off[q] += sign - sign * on


DIVISOR_STATE = np.dtype([("s", np.float64), ("t", np.float32), ("lvl", np.float32), ("base", np.float32),
                          ("lvl_f", np.float32), ("n", np.int32), ("n_f", np.int32)], align=True)
"""divisor_stream's per-pixel row, 32 bytes so that each event touches one cache line: running sum, last event
time - ts, net level, base level, level and event count at f, events. float32 is exact for times below 2**24 µs
(the caller checks the exposure) and for levels up to 2**24 events a pixel."""


@njit(cache=True, nogil=True)
def divisor_stream(t, x, y, p, width, height, mask, use_mask, ts, te, f, c, count_all, use_count_all, state, seen,
                   acc_on, acc_off, use_acc):
    """log D(c) per active pixel for c_on == c_off in ONE time-ordered pass, no sort and no exp per event.

    Per pixel: the net level n counted from ts, and a running sum of dwell * exp(c * (n - base)) read from a
    small table; the base moves up when n climbs more than the table above it (levels far below the base
    underflow harmlessly), so any event count stays finite. Events must lie in [ts, te]. `state` is scratch
    (npix rows of DIVISOR_STATE), `seen` (npix uint8) must come zeroed. With use_acc, the ON/OFF counts of the
    events after f are added to acc_on/acc_off.
    Returns (pixels in ascending order, log D, c * (n(te) - n(f)))."""
    npix = width * height
    k = 64
    ztab = np.empty(2 * k + 1, dtype=np.float64)
    for j in range(2 * k + 1):
        ztab[j] = math.exp(c * (j - k))
    n_act = 0
    for i in range(t.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            if use_count_all:
                count_all[q] += 1
            continue
        row = state[q]
        ti = np.float32(t[i] - ts)
        if seen[q] == 0:  # 1: active, 2: active and f passed
            seen[q] = 1
            row.s = 0.0
            row.t = 0.0
            row.lvl = 0.0
            row.base = 0.0
            row.n = 0
            n_act += 1
        if t[i] > f and seen[q] == 1:
            row.lvl_f = row.lvl
            row.n_f = row.n
            seen[q] = 2
        dwell = ti - row.t
        if dwell > 0.0:
            total = row.s
            if total == 0.0:  # first time with dwell: the base is this level, so the sum stays >= 1 µs
                row.base = row.lvl
            d = int(row.lvl - row.base)
            if d > k:  # far above the base: rebase upwards (log-sum-exp); only levels with dwell count
                total *= math.exp(-c * d)
                row.base = row.lvl
                d = 0
            row.s = total + dwell * (ztab[d + k] if d >= -k else math.exp(c * d))
        row.t = ti
        row.lvl += np.float32(1.0) if p[i] else np.float32(-1.0)
        row.n += 1
    pixels = np.empty(n_act, dtype=np.int64)
    log_d = np.empty(n_act, dtype=np.float64)
    delta_end = np.empty(n_act, dtype=np.float64)
    span = float(te - ts)
    r = 0
    for q in range(npix):  # ascending: sequential reads here and sequential writes for the caller
        if seen[q] == 0:
            continue
        row = state[q]
        total = row.s
        base = row.base
        if span - row.t > 0.0:
            if total == 0.0:
                base = row.lvl
            d = int(row.lvl - base)
            if d > k:
                total *= math.exp(-c * d)
                base = row.lvl
                d = 0
            total += (span - row.t) * (ztab[d + k] if d >= -k else math.exp(c * d))
        n_f = row.lvl_f if seen[q] == 2 else row.lvl
        if use_count_all:
            count_all[q] += row.n
        if use_acc and seen[q] == 2:
            n_after = row.n - row.n_f
            net_after = np.int64(row.lvl - row.lvl_f)
            acc_on[q] += (n_after + net_after) // 2
            acc_off[q] += (n_after - net_after) // 2
        pixels[r] = q
        log_d[r] = c * (base - n_f) + math.log(total / span)
        delta_end[r] = c * (row.lvl - n_f)
        r += 1
    return pixels, log_d, delta_end


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
def background_activity(t, x, y, width, height, last_t, dt_us, keep):
    """Background-activity filter: keep[i] when one of the 8 neighbours fired within dt_us before event i.
    last_t is a (height + 2, width + 2) int64 map of each pixel's latest event time (border never written)."""
    for i in range(t.size):
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        if xi >= width or yi >= height:
            keep[i] = False
            continue
        ti = t[i]
        ok = False
        for dy in range(3):
            for dx in range(3):
                if (dy != 1 or dx != 1) and ti - last_t[yi + dy, xi + dx] <= dt_us:
                    ok = True
        keep[i] = ok
        last_t[yi + 1, xi + 1] = ti


@njit(cache=True, nogil=True)
def _u8(v, v0, scale, bucket_u8, bucket_thr):
    """uint8 rendering of a log intensity without exp: bucket of v, plus one if v reaches the bucket's
    threshold (the tables hold every rounding threshold; a bucket holds at most one)."""
    b = (v - v0) * scale
    if b < 0.0:
        return np.uint8(0)
    if b >= bucket_u8.size:
        return np.uint8(255)
    i = int(b)
    return bucket_u8[i] + np.uint8(v >= bucket_thr[i])


@njit(cache=True, nogil=True)
def finish_frame_u8(img, sat, lut_log, lut_u8, pixels, log_d, delta_end, lo, hi, log_ref, deblurred, log_lat,
                    display, v0, scale, bucket_u8, bucket_thr):
    """One pass for what follows the divisor of a uint8 APS frame: log L(f) (log B minus log D at the active
    informative pixels, clipped), its uint8 image, the latent log image at te (plus the f->te exponent) and its
    uint8 image. Inactive pixels come from 256-entry tables of log(max(B, floor)) and its uint8 rendering;
    active ones are rendered through the bucket tables (v0, scale, bucket_u8, bucket_thr) instead of exp."""
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
        if i > 0 and i < sat:
            v = v - np.float32(log_d[r])
            v = min(max(v, lo), hi)
            log_ref[q] = v
            deblurred[q] = _u8(v, v0, scale, bucket_u8, bucket_thr)
        w = v + np.float32(delta_end[r])
        w = min(max(w, lo), hi)
        log_lat[q] = w
        display[q] = _u8(w, v0, scale, bucket_u8, bucket_thr)


@njit(cache=True, nogil=True)
def update_hot(hot_counts, frame_counts, decay, duration_us, min_rate_hz, rel_factor, hot):
    """hot_counts = decay * hot_counts + frame_counts (frame_counts is reset to 0), then the hot-pixel rule of
    edi.hot_pixel_mask on the result, written into `hot` (flat bool)."""
    total = 0.0
    n_active = 0
    for q in range(hot_counts.size):
        v = hot_counts[q] * decay + frame_counts[q]
        frame_counts[q] = 0
        hot_counts[q] = v
        if v > 0:
            total += v
            n_active += 1
    if n_active == 0 or duration_us <= 0:
        hot[:] = False
        return
    limit = rel_factor * (total / n_active)
    scale = 1e6 / duration_us
    for q in range(hot_counts.size):
        v = hot_counts[q]
        hot[q] = v * scale > min_rate_hz and v > limit


@njit(cache=True, nogil=True)
def select_pixels(x, y, width, height, keep):
    """Indices of the events whose pixel is in range and marked in `keep` (flat uint8), in input order."""
    out = np.empty(x.size, dtype=np.int64)
    m = 0
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        if keep[np.int64(y[i]) * width + x[i]]:
            out[m] = i
            m += 1
    return out[:m]


@njit(cache=True, nogil=True)
def select_and_count(x, y, p, width, height, keep, s0, s1, mask, use_mask, out_on, out_off, c0, c1, sign):
    """select_pixels on events [s0, s1) and count_events on events [c0, c1) (indices into the same arrays) in
    one pass over their union, which must be contiguous (the ranges overlap or touch)."""
    out = np.empty(max(s1 - s0, 0), dtype=np.int64)
    m = 0
    cuts = np.array([min(s0, c0), s0, s1, c0, c1, max(s1, c1)], dtype=np.int64)
    cuts.sort()
    for j in range(cuts.size - 1):  # pieces where both range tests are constant: a branch-light loop for each
        a = cuts[j]
        b = cuts[j + 1]
        if a >= b:
            continue
        do_sel = s0 <= a < s1
        do_cnt = c0 <= a < c1
        for i in range(a, b):
            if x[i] >= width or y[i] >= height:
                continue
            q = np.int64(y[i]) * width + x[i]
            if do_sel and keep[q]:
                out[m] = i
                m += 1
            if do_cnt and not (use_mask and mask[q]):
                on = np.int64(p[i])
                out_on[q] += sign * on
                out_off[q] += sign - sign * on
    return out[:m]


@njit(cache=True, nogil=True)
def pair_candidates(inf_p, inf_c, bp, bc, b_low, b_high, mask, use_mask, n_on, n_off, pix_p, pix_c):
    """Pixels (ascending) informative in both frames, with both B in [b_low, b_high], not masked, and with
    events between the frames or in either exposure table (pix_p, pix_c): the consistency residual candidates."""
    npix = bp.size
    in_table = np.zeros(npix, dtype=np.uint8)
    for r in range(pix_p.size):
        in_table[pix_p[r]] = 1
    for r in range(pix_c.size):
        in_table[pix_c[r]] = 1
    out = np.empty(npix, dtype=np.int64)
    m = 0
    for q in range(npix):
        if not (inf_p[q] and inf_c[q]):
            continue
        if not (bp[q] >= b_low and bp[q] <= b_high and bc[q] >= b_low and bc[q] <= b_high):
            continue
        if use_mask and mask[q]:
            continue
        if n_on[q] + n_off[q] > 0 or in_table[q]:
            out[m] = q
            m += 1
    return out[:m]
