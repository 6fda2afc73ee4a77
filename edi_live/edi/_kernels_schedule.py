"""numba kernels of the scheduled residual estimate (see edi_live.edi.residual_schedule): one pass over a pair's
events that turns each pixel's gaps between events into the frames at which its estimate changes, and the
sorting of those changes by frame (edi_live.edi._kernels_fused.render_frames applies them).

Private to edi_live.edi (see edi_live.edi.residual_schedule; edi_live.edi.residual is the reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _first_at_or_after


@njit(cache=True, nogil=True)
def _value(t, ta, ca, tb, cb, seen_from, seen_to, table_a, table_b, a_unknown):
    """The residual estimate at t in the gap from the event (ta, ca) to the event (tb, cb): what
    _kernels_residual.residual_at computes for one pixel (the same float operations)."""
    if ta < seen_from:
        return np.float32(0.0)
    if tb > seen_to:
        return a_unknown * ca
    nb = table_a.size
    span = tb - ta
    i = min(max(int((t - ta) * (nb / span)), 0), nb - 1) if span > 0 else nb - 1
    return table_a[i] * ca + table_b[i] * cb


@njit(cache=True, nogil=True)
def _gallop(times, lo, hi, value):
    """The first index in [lo, hi) with times[index] >= value (hi if none): a few steps (the next change is
    mostly a frame or two on), then binary search."""
    stop = min(hi, lo + 4)
    while lo < stop:
        if times[lo] >= value:
            return lo
        lo += 1
    return _first_at_or_after(times, value, lo, hi)


@njit(cache=True, nogil=True)
def _copy_state(last_t, last_p, to_t, to_p):
    for q in range(last_t.size):  # an explicit loop: numba's slice assignment copies several times slower
        to_t[q] = last_t[q]
        to_p[q] = last_p[q]


@njit(cache=True, nogil=True)
def schedule(x, y, p, tt, start, width, height, mask, use_mask, last_t, last_p, snap_t, snap_last_t, snap_last_p,
             frames, span, forget_after, never, c_on, c_off, table_a, table_b, a_unknown, samples, s_row, s_from,
             s_to, acc, cur, ent_f, ent_q, ent_v):
    """Walk the events start.. (time-ordered, all after last_t) from each pixel's last event before them
    (last_t, last_p: time and polarity 1 ON / 2 OFF / 0 none; updated in place to the end of the events) and
    emit, per pixel, the frames at which its residual estimate changes from cur and the new value (ent_*, each
    pixel's in time order; cur holds the estimate before the first frame and is left at the last frame's).
    snap_last_*: each pixel's last event at or before snap_t. acc[s_row[s]] += the estimate at samples[s]
    (ascending; seen s_from[s]..s_to[s]). Returns the number of entries (more than ent_f.size: they did not fit,
    nothing else is valid)."""
    npx = width * height
    n_ent = 0
    snapped = False
    n = frames.size
    nb = table_a.size
    n_ev = tt.size
    n_s = samples.size
    # the first frame / sample at or after each pixel's last event (all of the carried ones are before both)
    f_after = np.zeros(npx, np.int32)
    s_after = np.zeros(npx, np.int32)
    jf = 0  # the first frame / sample at or after the current event (times ascend)
    js = 0
    for i in range(start, n_ev + npx):  # each event closes its pixel's gap; then every pixel's open gap
        if i < n_ev:
            tb = tt[i]
            if not snapped and tb > snap_t:
                _copy_state(last_t, last_p, snap_last_t, snap_last_p)
                snapped = True
            if x[i] >= width or y[i] >= height:
                continue
            q = np.int64(y[i]) * width + x[i]
            if use_mask and mask[q]:
                continue
            cb = c_on if p[i] else -c_off
            while jf < n and frames[jf] < tb:
                jf += 1
            while js < n_s and samples[js] < tb:
                js += 1
        else:
            if not snapped:
                _copy_state(last_t, last_p, snap_last_t, snap_last_p)
                snapped = True
            q = np.int64(i - n_ev)
            tb, cb = never, np.float32(0.0)
            jf, js = n, n_s
        if last_p[q] != 0:  # the gap [ta, tb) of pixel q holds frames f_after[q]..jf-1, samples s_after[q]..js-1
            ta = last_t[q]
            ca = c_on if last_p[q] == 1 else -c_off
            for s in range(s_after[q], js):
                acc[s_row[s], q] += _value(samples[s], ta, ca, tb, cb, s_from[s], s_to[s], table_a, table_b,
                                           a_unknown)
            j = f_after[q]
            if j < jf:
                forget = ta + forget_after + 1  # from here on the last event is not seen: 0
                known = tb - span  # from here on the next event is seen
                t_j = frames[j]
                if t_j < known and t_j < forget:  # the next event not seen yet
                    v = a_unknown * ca
                    if v != cur[q]:
                        if n_ent < ent_f.size:
                            ent_f[n_ent], ent_q[n_ent], ent_v[n_ent] = j, q, v
                        n_ent += 1
                        cur[q] = v
                    j = _gallop(frames, j + 1, jf, min(known, forget))
                if j < jf and frames[j] < forget:  # both seen: the table's bin of x
                    length = tb - ta
                    to_bin = nb / length  # one division per gap
                    per_bin = length * (1.0 / nb)
                    while True:
                        b = min(int((frames[j] - ta) * to_bin), nb - 1)
                        v = table_a[b] * ca + table_b[b] * cb
                        if v != cur[q]:
                            if n_ent < ent_f.size:
                                ent_f[n_ent], ent_q[n_ent], ent_v[n_ent] = j, q, v
                            n_ent += 1
                            cur[q] = v
                        # a little before the next bin's boundary: float rounding must not let it be passed over
                        nxt = forget if b == nb - 1 else min(forget, ta + np.int64((b + 1) * per_bin) - 1)
                        j = _gallop(frames, j + 1, jf, nxt)
                        if j >= jf or frames[j] >= forget:
                            break
                if j < jf and cur[q] != 0.0:  # forgotten
                    if n_ent < ent_f.size:
                        ent_f[n_ent], ent_q[n_ent], ent_v[n_ent] = j, q, np.float32(0.0)
                    n_ent += 1
                    cur[q] = 0.0
        if i < n_ev:
            last_t[q] = tb
            last_p[q] = 1 if p[i] else 2
            f_after[q] = jf
            s_after[q] = js
    return n_ent


@njit(cache=True, nogil=True)
def by_frame(ent_f, ent_q, ent_v, n_ent, n_frames, offsets, q_sorted, v_sorted):
    """Counting sort of the entries by frame: frame j's are q_sorted/v_sorted[offsets[j]:offsets[j + 1]], in
    emission order."""
    offsets[:] = 0
    for e in range(n_ent):
        offsets[ent_f[e] + 1] += 1
    for j in range(n_frames):
        offsets[j + 1] += offsets[j]
    fill = offsets[:-1].copy()
    for e in range(n_ent):
        k = fill[ent_f[e]]
        q_sorted[k] = ent_q[e]
        v_sorted[k] = ent_v[e]
        fill[ent_f[e]] = k + 1
