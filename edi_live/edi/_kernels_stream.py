"""numba kernels that stream over events in time order: latent propagation with the display refresh, ON/OFF
counting, the single-pass log divisor for one c (with the f -> te jump), and the fused frame finish.

Private to edi_live.edi (see its public functions and their numpy references).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

@njit(cache=True, nogil=True)
def propagate(x, y, p, width, height, mask, use_mask, flat, d_on, d_off, lo, hi, disp, use_disp, gain, v0, scale,
              bucket_u8, bucket_thr, acc_on, acc_off, use_acc):
    """The display is rendered from the float64 sum (before its float32 rounding into `flat`) through the
    float64 bucket tables of display_u8 (latent.display_buckets), the same values as display_u8 without an exp
    per event; with empty tables (a gain that has none) by display_u8's exp itself."""
    use_table = bucket_u8.size > 0
    applied = 0
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        on = p[i]
        v = flat[q] + (d_on if on else d_off)
        v = _clip(v, lo, hi)
        flat[q] = v
        if use_disp:
            disp[q] = _u8(v, v0, scale, bucket_u8, bucket_thr) if use_table else _exp_u8(v, gain)
        if use_acc:  # branch-free, as in count_events
            o = np.int64(on)
            acc_on[q] += o
            acc_off[q] += 1 - o
        applied += 1
    return applied


@njit(cache=True, nogil=True, inline="always")
def _first_at_or_after(t, value, lo, hi):
    """The first index in [lo, hi) of time-ordered t with t >= value (hi if none), by bisection."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if t[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, nogil=True, inline="always")
def _exp_u8(v, gain):
    z = gain * math.exp(min(v, 6.0)) + 0.5
    if z > 255.0:
        z = 255.0
    return np.uint8(z)


@njit(cache=True, nogil=True)
def display_u8(v, gain, out):
    """out[i] = clip(gain * exp(v[i]), 0, 255) rounded, in float64 (what propagate's tables stand for)."""
    for i in range(v.size):
        out[i] = _exp_u8(v[i], gain)


@njit(cache=True, nogil=True)
def display_u8_table(v, v0, scale, bucket_u8, bucket_thr, out):
    """out[i] as propagate renders v[i] (float64) through the bucket tables."""
    for i in range(v.size):
        out[i] = _u8(v[i], v0, scale, bucket_u8, bucket_thr)


@njit(cache=True, nogil=True)
def count_events(x, y, p, width, height, mask, use_mask, out_on, out_off, sign, floor):
    """`floor`: counts held at >= 0 as they go (with counts >= 0 before: the result floored at 0 once)."""
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        on = np.int64(p[i])  # branch-free: polarities are unpredictable (two adds beat a mispredict)
        out_on[q] += sign * on
        out_off[q] += sign - sign * on
        if floor:
            out_on[q] = max(out_on[q], 0)
            out_off[q] = max(out_off[q], 0)


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
    Returns (pixels in ascending order, log D, c * (n(te) - n(f))).
    The same as divisor_feed over the events (in any number of time-ordered parts) then divisor_finish."""
    n_act = divisor_feed(t, x, y, p, width, height, mask, use_mask, ts, f, c, count_all, use_count_all, state, seen)
    return divisor_finish(width, height, ts, te, c, count_all, use_count_all, state, seen, n_act, acc_on, acc_off,
                          use_acc)


@njit(cache=True, nogil=True, inline="always")
def _level_table(c, k):
    ztab = np.empty(2 * k + 1, dtype=np.float64)
    for j in range(2 * k + 1):
        ztab[j] = math.exp(c * (j - k))
    return ztab


@njit(cache=True, nogil=True)
def divisor_feed(t, x, y, p, width, height, mask, use_mask, ts, f, c, count_all, use_count_all, state, seen):
    """divisor_stream's pass over (a time-ordered part of) the exposure's events; returns the pixels it made
    active. Every part of one exposure must come with the same mask, c, ts and f, in time order."""
    k = 64
    ztab = _level_table(c, k)
    n_act = 0
    for i in range(t.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            if use_count_all:  # counted at the finish: a fed state may be dropped unfinished
                if seen[q] == 0:  # 3: masked, its events counted in n
                    seen[q] = 3
                    state[q].n = 0
                state[q].n += 1
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
    return n_act


@njit(cache=True, nogil=True)
def divisor_finish(width, height, ts, te, c, count_all, use_count_all, state, seen, n_act, acc_on, acc_off, use_acc):
    """divisor_stream's results from the state divisor_feed left (`n_act`: the active pixels it reported)."""
    npix = width * height
    k = 64
    ztab = _level_table(c, k)
    pixels = np.empty(n_act, dtype=np.int64)
    log_d = np.empty(n_act, dtype=np.float64)
    delta_end = np.empty(n_act, dtype=np.float64)
    span = float(te - ts)
    r = 0
    for q in range(npix):  # ascending: sequential reads here and sequential writes for the caller
        if seen[q] == 0:
            continue
        row = state[q]
        if seen[q] == 3:
            count_all[q] += row.n
            continue
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



@njit(cache=True, nogil=True, inline="always")
def _clip(v, lo, hi):
    """v held within [lo, hi] (the log-intensity state's bounds)."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


@njit(cache=True, nogil=True, inline="always")
def _u8(v, v0, scale, bucket_u8, bucket_thr):
    """uint8 rendering of a log intensity without exp: bucket of v, plus one if v reaches the bucket's
    threshold (the tables hold every rounding threshold; a bucket holds at most one)."""
    b = (v - v0) * scale
    if not b >= 0.0:  # below the first step, or NaN (rendered 0, as the exp formula's conversion gives)
        return np.uint8(0)
    if b >= bucket_u8.size:
        return np.uint8(255)
    i = int(b)
    return bucket_u8[i] + np.uint8(v >= bucket_thr[i])


@njit(cache=True, nogil=True)
def finish_frame_u8(img, sat, dark, lut_log, lut_u8, pixels, log_d, shown_d, shown_jump, lo, hi, log_ref, log_shown,
                    deblurred, log_lat, display, v0, scale, bucket_u8, bucket_thr):
    """One pass for what follows the divisor of a uint8 APS frame. log_ref: log L(f), log B minus each active
    informative pixel's own log D (`log_d`), clipped. log_shown and its uint8 image `deblurred`: the same with the
    log D shown (`shown_d`: the same values for per-pixel EDI, edi.smoothing's median otherwise). The latent log
    image at te and its uint8 image `display`: the shown L(f) plus `shown_jump` (the f->te exponent, or the
    smoothed one). Pixels at or below `dark` (the black level) or at/above `sat` are not divided. Inactive pixels
    come from 256-entry tables of log(max(B - black level, floor)) and its uint8 rendering; active ones are rendered
    through the bucket tables (v0, scale, bucket_u8, bucket_thr) instead of exp. log_shown may be log_ref itself."""
    for q in range(img.size):
        i = img[q]
        v = lut_log[i]
        log_ref[q] = v
        log_shown[q] = v
        log_lat[q] = v
        u = lut_u8[i]
        deblurred[q] = u
        display[q] = u
    for r in range(pixels.size):
        q = pixels[r]
        i = img[q]
        s = lut_log[i]
        if i > dark and i < sat:
            log_ref[q] = _clip(s - np.float32(log_d[r]), lo, hi)
            s = _clip(s - np.float32(shown_d[r]), lo, hi)
            log_shown[q] = s
            deblurred[q] = _u8(s, v0, scale, bucket_u8, bucket_thr)
        w = _clip(s + np.float32(shown_jump[r]), lo, hi)
        log_lat[q] = w
        display[q] = _u8(w, v0, scale, bucket_u8, bucket_thr)


DIVISOR_STATE_TWO = np.dtype([("s", np.float64), ("w", np.float64), ("base", np.float64), ("t", np.float32),
                              ("on", np.int32), ("off", np.int32), ("on_f", np.int32), ("off_f", np.int32),
                              ("pad", np.int32)], align=True)
"""divisor_stream_two's per-pixel row (48 bytes): running sum of dwell * w, w = exp(E - base) with E = c_on*on -
c_off*off since ts, the log-scale base, last event time - ts, and the ON/OFF counts now and at f."""


@njit(cache=True, nogil=True, inline="always")
def _add_dwell(row, dwell, c_on, c_off):
    """row.s += dwell * exp(E - base), E = c_on*on - c_off*off. Fast path: the weight w kept by multiplication is
    in range. Otherwise E - base comes from the counts: far above the base, rebase up (the sum so far scales down,
    possibly to 0, harmlessly: this dwell dominates it); far below with a sum already there, the term vanishes;
    no sum yet, the base becomes this level. w is then re-derived, so it recovers after any excursion."""
    w = row.w
    if 1e-150 <= w <= 1e150:
        row.s += dwell * w
        return
    lw = c_on * row.on - c_off * row.off - row.base
    if row.s == 0.0:
        row.s = dwell
        row.base += lw
        row.w = 1.0
    elif lw > 0.0:
        row.s = row.s * math.exp(-lw) + dwell
        row.base += lw
        row.w = 1.0
    else:
        w = math.exp(lw)
        row.s += dwell * w
        row.w = w


@njit(cache=True, nogil=True)
def divisor_stream_two(t, x, y, p, width, height, mask, use_mask, ts, te, f, c_on, c_off, count_all, use_count_all,
                       state, seen, acc_on, acc_off, use_acc):
    """divisor_stream for separate thresholds: each event multiplies the pixel's weight w by exp(c_on) or
    exp(-c_off) (two constants, no exp per event); see _add_dwell for how any event count stays finite. Same
    arguments and results; the same as divisor_feed_two over the events (in parts) then divisor_finish_two."""
    n_act = divisor_feed_two(t, x, y, p, width, height, mask, use_mask, ts, f, c_on, c_off, count_all, use_count_all,
                             state, seen)
    return divisor_finish_two(width, height, ts, te, c_on, c_off, count_all, use_count_all, state, seen, n_act,
                              acc_on, acc_off, use_acc)


@njit(cache=True, nogil=True)
def divisor_feed_two(t, x, y, p, width, height, mask, use_mask, ts, f, c_on, c_off, count_all, use_count_all, state,
                     seen):
    """divisor_stream_two's pass over (a time-ordered part of) the exposure's events (see divisor_feed)."""
    e_on = math.exp(c_on)
    e_off = math.exp(-c_off)
    n_act = 0
    for i in range(t.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            if use_count_all:  # counted at the finish (see divisor_feed); 3: masked, its events counted in on
                if seen[q] == 0:
                    seen[q] = 3
                    state[q].on = 0
                state[q].on += 1
            continue
        row = state[q]
        ti = np.float32(t[i] - ts)
        if seen[q] == 0:  # 1: active, 2: active and f passed
            seen[q] = 1
            row.s = 0.0
            row.w = 1.0
            row.base = 0.0
            row.t = 0.0
            row.on = 0
            row.off = 0
            n_act += 1
        if t[i] > f and seen[q] == 1:
            row.on_f = row.on
            row.off_f = row.off
            seen[q] = 2
        dwell = ti - row.t
        if dwell > 0.0:
            _add_dwell(row, dwell, c_on, c_off)
        row.t = ti
        on = np.int32(p[i])  # no branch on the polarity (unpredictable: 12.3 -> 9.6 ns a fed event on demo6)
        row.on += on
        row.off += 1 - on
        row.w *= e_on if on else e_off
    return n_act


@njit(cache=True, nogil=True)
def divisor_finish_two(width, height, ts, te, c_on, c_off, count_all, use_count_all, state, seen, n_act, acc_on,
                       acc_off, use_acc):
    """divisor_stream_two's results from the state divisor_feed_two left."""
    npix = width * height
    pixels = np.empty(n_act, dtype=np.int64)
    log_d = np.empty(n_act, dtype=np.float64)
    delta_end = np.empty(n_act, dtype=np.float64)
    span = float(te - ts)
    r = 0
    for q in range(npix):
        if seen[q] == 0:
            continue
        row = state[q]
        if seen[q] == 3:
            count_all[q] += row.on
            continue
        if span - row.t > 0.0:
            _add_dwell(row, span - row.t, c_on, c_off)
        total = row.s
        e_te = c_on * row.on - c_off * row.off
        e_f = c_on * row.on_f - c_off * row.off_f if seen[q] == 2 else e_te
        if use_count_all:
            count_all[q] += row.on + row.off
        if use_acc and seen[q] == 2:
            acc_on[q] += row.on - row.on_f
            acc_off[q] += row.off - row.off_f
        pixels[r] = q
        log_d[r] = math.log(total / span) + row.base - e_f
        delta_end[r] = e_te - e_f
        r += 1
    return pixels, log_d, delta_end
