"""The EDI sums that the frame-to-frame consistency estimator of c evaluates over pairs of consecutive frames:
which pixels can take part, and the robust residual cost for one c.

residual_i = log B_cur - log B_prev - (c * net_i + log D_cur,i(c) - log D_prev,i(c)), cost = sum w_i sqrt(d^2 + r^2)
"""

from __future__ import annotations

import numpy as np

from edi_live.edi import _backend, _kernels_levels
from edi_live.edi._backend import LEVEL_CAP
from edi_live.edi.levels import LevelTable


def pair_candidates(prev_informative: np.ndarray, cur_informative: np.ndarray, b_prev: np.ndarray,
                    b_cur: np.ndarray, b_low: float, b_high: float, mask: np.ndarray | None, n_on: np.ndarray,
                    n_off: np.ndarray, prev_pixels: np.ndarray, cur_pixels: np.ndarray) -> np.ndarray:
    """Flat pixel indices (ascending) informative in both frames, with both B (flat, 8-bit scale) in
    [b_low, b_high], not masked (flat bool), and with events between the frames (n_on + n_off > 0) or in either
    exposure (the tables' active pixels): the pixels whose residual says something about c."""
    if _backend.have_numba():
        def as_u8(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(a, dtype=bool).reshape(-1).view(np.uint8)

        m = as_u8(mask) if mask is not None else _backend.NO_MASK
        return _kernels_levels.pair_candidates(as_u8(prev_informative), as_u8(cur_informative), b_prev, b_cur,
                                               np.float32(b_low), np.float32(b_high), m, mask is not None, n_on,
                                               n_off, prev_pixels, cur_pixels)
    ok = prev_informative.reshape(-1) & cur_informative.reshape(-1)
    ok &= (b_prev >= b_low) & (b_prev <= b_high) & (b_cur >= b_low) & (b_cur <= b_high)
    if mask is not None:
        ok &= ~mask
    signal = (n_on + n_off) > 0
    signal[prev_pixels] = True
    signal[cur_pixels] = True
    return np.flatnonzero(ok & signal)


def consistency_cost(c: float, dlog_b: np.ndarray, net: np.ndarray, weight: np.ndarray, delta2: float,
                     prev: LevelTable, prev_rows: np.ndarray, cur: LevelTable, cur_rows: np.ndarray,
                     terms: np.ndarray | None = None) -> float:
    """The cost for c_on == c_off == c, without temporaries. `prev`/`cur` are the level tables restricted to the
    residuals' pixels that were active, `*_rows` the residual index of each of their rows. `terms`, if given (of
    dlog_b's size), receives every residual's term. Kernel only: ConsistencyContrast.terms is its numpy reference
    (and serves c_on != c_off)."""
    out = np.zeros(0) if terms is None else terms
    return _kernels_levels.consistency_cost(float(c), dlog_b, net, weight, delta2, prev.lvl_start, prev.lvl_min,
                                            prev.lvl_frac, prev_rows, cur.lvl_start, cur.lvl_min, cur.lvl_frac,
                                            cur_rows, LEVEL_CAP, out)
