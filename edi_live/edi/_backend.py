"""Which implementation the EDI functions run, the numeric limits they share, and the argument forms of the kernels.

numba is a hard dependency: every public function of edi_live.edi runs its compiled kernel. Each also keeps a
plain numpy reference implementation of the same contract; `numpy_reference()` (or the environment variable
EDI_LIVE_NO_NUMBA=1, read once at import) switches the whole package to those, which is how the tests check
the kernels against them and how tools/bench_edi_speed.py measures what the kernels buy.
"""

from __future__ import annotations

import contextlib
import os
from typing import Iterator

import numpy as np

LEVEL_CAP = 256
"""Pixels whose net level range is wider than this are evaluated with a per-entry log-sum-exp (no lookup table)."""
LOG_MIN = -30.0
LOG_MAX = 30.0
"""Bounds of the log-intensity state (8-bit scale): keeps every exp() finite whatever the events say."""
DARK_FLOOR = 0.25
"""B values below this (8-bit scale) are treated as this, so log B is finite."""

_kernels = not os.environ.get("EDI_LIVE_NO_NUMBA")

NO_MASK = np.zeros(0, dtype=np.uint8)
NO_COUNTS = np.zeros(0, dtype=np.int64)


def have_numba() -> bool:
    """True when the compiled kernels run (False inside numpy_reference())."""
    return _kernels


@contextlib.contextmanager
def numpy_reference() -> Iterator[None]:
    """Run every edi_live.edi function on its numpy reference implementation inside the block (not thread-safe:
    for tests and benchmarks, never while a node runs)."""
    global _kernels
    before, _kernels = _kernels, False
    try:
        yield
    finally:
        _kernels = before


def mask_arg(mask: np.ndarray | None) -> tuple[np.ndarray, bool]:
    """A (H, W) bool mask (or None) as the kernels take it: a flat uint8 view and a 'use it' flag."""
    if mask is None:
        return NO_MASK, False
    return np.ascontiguousarray(mask, dtype=bool).reshape(-1).view(np.uint8), True


def counts_arg(counts: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Optional (n_on, n_off) flat int64 accumulators as the kernels take them."""
    if counts is None:
        return NO_COUNTS, NO_COUNTS, False
    return counts[0], counts[1], True
