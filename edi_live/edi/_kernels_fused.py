"""numba kernels of the fused (two-frame) latent image: the plan per pair of frames, event propagation with
per-pixel ON/OFF steps, and the time term, or all of a pair's frames in one call with the residual estimate's
changes (edi_live.edi.residual_schedule); the display through the bucket tables (to_uint8's rounding, no exp).

Private to edi_live.edi (see edi_live.edi.fused and its numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from edi_live.edi._kernels_stream import _clip, _u8


@njit(cache=True, nogil=True, inline="always")
def _step(i, x, y, p, width, height, mask, use_mask, flat, step_on, step_off, lo, hi):
    """Event i moves its pixel's flat[q] by the pixel's ON or OFF step; returns q, or -1 for an event off the
    sensor or masked."""
    if x[i] >= width or y[i] >= height:
        return -1
    q = np.int64(y[i]) * width + x[i]
    if use_mask and mask[q]:
        return -1
    flat[q] = _clip(flat[q] + (step_on[q] if p[i] else step_off[q]), lo, hi)
    return q


@njit(cache=True, nogil=True)
def propagate_steps(x, y, p, width, height, mask, use_mask, flat, step_on, step_off, lo, hi, disp, v0, scale,
                    bucket_u8, bucket_thr):
    for i in range(x.size):
        q = _step(i, x, y, p, width, height, mask, use_mask, flat, step_on, step_off, lo, hi)
        if q >= 0:
            disp[q] = _u8(flat[q], v0, scale, bucket_u8, bucket_thr)


@njit(cache=True, nogil=True)
def pair_sums(x, y, p, width, height, mask, use_mask, c_on, c_off, delta, mass):
    """delta += c_on (ON) / -c_off (OFF) and mass += c_on / c_off per event, flat float32 per pixel."""
    for i in range(x.size):
        if x[i] >= width or y[i] >= height:
            continue
        q = np.int64(y[i]) * width + x[i]
        if use_mask and mask[q]:
            continue
        if p[i]:
            delta[q] += c_on
            mass[q] += c_on
        else:
            delta[q] -= c_off
            mass[q] += c_off


@njit(cache=True, nogil=True)
def plan_pixels(r0, r1, e01, mass, inf0, inf1, a, c_on, c_off, lo, hi, start, step_on, step_off, time_term,
                start_u8, v0, scale, bucket_u8, bucket_thr):
    """The per-pixel part of a fusion plan in one pass (flat float32 arrays; see edi_live.edi.fused.fusion_plan),
    with the uint8 image of its start."""
    one = np.float32(1.0)
    for q in range(r0.size):
        d = r1[q] - r0[q] - e01[q]
        s = r0[q]
        share = np.float32(0.0)
        if inf0[q] == inf1[q]:
            share = d / (mass[q] + a)
        elif inf1[q]:  # only frame k+1 informative: it is taken whole
            s = s + d
        s = _clip(s, lo, hi)
        start[q] = s
        start_u8[q] = _u8(s, v0, scale, bucket_u8, bucket_thr)
        step_on[q] = c_on * (one + share)
        step_off[q] = -c_off * (one - share)
        time_term[q] = a * share


@njit(cache=True, nogil=True)
def shift_time(flat, term, dtau, lo, hi, disp, v0, scale, bucket_u8, bucket_thr):
    """flat += dtau * term, clipped, and the uint8 display at the pixels whose time term is not zero."""
    for q in range(flat.size):
        t = term[q]
        if t == 0.0:
            continue
        v = flat[q] + dtau * t
        v = _clip(v, lo, hi)
        flat[q] = v
        disp[q] = _u8(v, v0, scale, bucket_u8, bucket_thr)


@njit(cache=True, nogil=True)
def render_frames(x, y, p, tt, pos, width, height, mask, use_mask, frames, dtau, flat, step_on, step_off, term,
                  res, disp, init_disp, offsets, q_sorted, v_sorted, lo, hi, out, v0, scale, bucket_u8, bucket_thr):
    """The fused frames at `frames` (ascending): per frame, the events up to it (from index pos) moved by their
    pixel's steps, the time term moved by dtau[j] (0: not moved), the residual changes of the frame, and the
    display u8(flat + res) copied to out[j]. flat, res and disp are updated in place (`init_disp`: disp made
    u8(flat + res) first, when res does not start at 0)."""
    n = frames.size
    if init_disp:
        for q in range(flat.size):
            w = flat[q] + res[q]
            w = _clip(w, lo, hi)
            disp[q] = _u8(w, v0, scale, bucket_u8, bucket_thr)
    for j in range(n):
        t_j = frames[j]
        while pos < tt.size and tt[pos] <= t_j:
            q = _step(pos, x, y, p, width, height, mask, use_mask, flat, step_on, step_off, lo, hi)
            pos += 1
            if q >= 0:
                disp[q] = _u8(_clip(flat[q] + res[q], lo, hi), v0, scale, bucket_u8, bucket_thr)
        if dtau[j] != 0.0:
            for q in range(flat.size):
                k = term[q]
                if k == 0.0:
                    continue
                v = flat[q] + dtau[j] * k
                v = _clip(v, lo, hi)
                flat[q] = v
                v = v + res[q]
                v = _clip(v, lo, hi)
                disp[q] = _u8(v, v0, scale, bucket_u8, bucket_thr)
        for k in range(offsets[j], offsets[j + 1]):
            q = q_sorted[k]
            r = v_sorted[k]
            res[q] = r
            w = flat[q] + r
            w = _clip(w, lo, hi)
            disp[q] = _u8(w, v0, scale, bucket_u8, bucket_thr)
        for q in range(disp.size):  # an explicit loop: numba's slice assignment copies ~8x slower
            out[j, q] = disp[q]
    return pos
