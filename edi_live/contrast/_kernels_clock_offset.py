"""Compiled lookup of the clock-offset fit (edi_live.contrast.clock_offset): where each pixel's exposure-sum
segments hold the asked times, searched within the pixel's own entries instead of the whole table."""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def last_at_or_before(key: np.ndarray, first: np.ndarray, row_key: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(pixels, queries) int64: for pixel i and time q[k], the index of the last entry of `key` (ascending) at or
    before row_key[i] + q[k], searched among pixel i's entries key[first[i]:first[i + 1]] only (every asked key
    lies within the pixel's range, whose first entry it never precedes)."""
    n = row_key.size
    out = np.empty((n, q.size), np.int64)
    for i in range(n):
        a = first[i]
        b = first[i + 1]
        for k in range(q.size):
            v = row_key[i] + q[k]
            lo = a
            hi = b
            while lo < hi:
                mid = (lo + hi) // 2
                if key[mid] <= v:
                    lo = mid + 1
                else:
                    hi = mid
            out[i, k] = lo - 1
    return out


@numba.njit(cache=True, nogil=True)
def integrals_at(key: np.ndarray, first: np.ndarray, row_key: np.ndarray, q: np.ndarray, intercept: np.ndarray,
                 slope: np.ndarray, lo: int) -> np.ndarray:
    """(pixels, queries): intercept[j] + slope[j] * (q[k] - lo), j = last_at_or_before's index."""
    j = last_at_or_before(key, first, row_key, q)
    out = np.empty(j.shape)
    for i in range(j.shape[0]):
        for k in range(q.size):
            out[i, k] = intercept[j[i, k]] + slope[j[i, k]] * (q[k] - lo)
    return out
