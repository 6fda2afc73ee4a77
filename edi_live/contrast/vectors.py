"""Vector reductions for the estimators, without BLAS.

numpy's `dot` hands long vectors to OpenBLAS, which splits them over its thread pool; those threads then spin,
waiting for more work, for a while after every call. In the node that made the black-level fit (a few dozen dot
products of ~10k-element vectors per frame pair) cost 2.9 s of CPU per 6 s of a replay on a 2-core machine, all of
it spinning (measured with OPENBLAS_NUM_THREADS=1: 10.35 -> 7.25 CPU-s). einsum's own loop does the same sum on
the calling thread.
"""

from __future__ import annotations

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """sum(a * b) of two 1-D arrays, on the calling thread."""
    return float(np.einsum("i,i->", a, b))
