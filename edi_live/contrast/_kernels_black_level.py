"""Compiled kernel of the black-level profile (edi_live.contrast.black_level): one grid point's c and cost in a
few passes over the quiet samples, without the temporaries of the numpy reference (~14 ms a fit at 240x180)."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def profile_point(b_prev: np.ndarray, b_cur: np.ndarray, net: np.ndarray, b: float, delta: float,
                  iterations: int, miss: float, bound: float) -> tuple[float, float]:
    """(c, cost) at black level b: black_level.fit_c then the sum of black_level.black_level_terms; cost inf when
    c is not positive, or once the running sum passes `bound` (the terms are >= 0: the cost would be larger;
    math.inf: never). No default: an omitted argument is a numba specialisation of its own, which the warm-up
    would have to compile apart."""
    n = net.size
    moving = np.empty(n, np.int64)  # only pixels with a net count enter the regression (N = 0 adds nothing)
    d_moving = np.empty(n)  # their log ratios; the others' are taken in the cost's pass (skipped past `bound`)
    m = 0
    dn = 0.0
    nn = 0.0
    for i in range(n):
        if net[i] != 0.0 and b_prev[i] > b + 1.0 and b_cur[i] > b + 1.0:
            d = math.log((b_cur[i] - b) / (b_prev[i] - b))
            moving[m] = i
            d_moving[m] = d
            m += 1
            dn += d * net[i]
            nn += net[i] * net[i]
    if nn <= 0:
        return math.nan, math.inf
    c = dn / nn
    for _ in range(iterations):
        if not c > 0:
            return math.nan, math.inf
        num = 0.0
        den = 0.0
        for k in range(m):
            i = moving[k]
            r = (d_moving[k] - c * net[i]) / (c * delta)
            w = 1.0 / math.sqrt(1.0 + r * r)
            num += w * d_moving[k] * net[i]
            den += w * net[i] * net[i]
        c = num / max(den, 1e-12)
    if not c > 0:
        return math.nan, math.inf
    cost = 0.0
    k = 0
    for i in range(n):
        if k < m and moving[k] == i:
            r = d_moving[k] / c - net[i]
            k += 1
        elif b_prev[i] > b + 1.0 and b_cur[i] > b + 1.0:
            r = math.log((b_cur[i] - b) / (b_prev[i] - b)) / c - net[i]
        else:
            r = miss
        cost += math.sqrt(delta * delta + r * r) - delta
        if cost > bound:
            return c, math.inf
    return c, cost
