"""One-dimensional searches for c: golden section, a coarse geometric grid then golden section, and the cost
wrapper that also exposes its per-pixel terms (for z tests on the cost's own noise)."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def golden_section(fn: Callable[[float], float], lo: float, hi: float, *, tol: float = 1e-3,
                   max_evals: int = 40) -> tuple[float, float, int]:
    """Minimise a unimodal fn on [lo, hi]; returns (x, fn(x), evaluations)."""
    a, b = lo, hi
    x1 = b - GOLDEN * (b - a)
    x2 = a + GOLDEN * (b - a)
    f1, f2 = fn(x1), fn(x2)
    n = 2
    while b - a > tol and n < max_evals:
        if f1 <= f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - GOLDEN * (b - a)
            f1 = fn(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + GOLDEN * (b - a)
            f2 = fn(x2)
        n += 1
    return (x1, f1, n) if f1 <= f2 else (x2, f2, n)


def grid_then_golden(fn: Callable[[float], float], lo: float, hi: float, *, n_grid: int = 8,
                     tol: float = 1e-3) -> tuple[float, int]:
    """Coarse geometric grid (robust to a non-unimodal criterion), then golden section around the best point."""
    grid = np.geomspace(lo, hi, n_grid)
    vals = [fn(float(c)) for c in grid]
    i = int(np.argmin(vals))
    a = float(grid[max(i - 1, 0)])
    b = float(grid[min(i + 1, n_grid - 1)])
    x, fx, n = golden_section(fn, a, b, tol=tol)
    if vals[i] < fx:
        x = float(grid[i])
    return x, n_grid + n


def three_point_fit(fn: Callable[[float], float], c: float, step: float) -> bool:
    mid = fn(c)
    return mid <= min(fn(c * (1.0 - step)), fn(c * (1.0 + step)))


class Cost:
    """cost(c_on, c_off) -> float, plus .terms(c_on, c_off) -> the per-pixel terms that sum to it."""

    __slots__ = ("_fn", "terms")

    def __init__(self, fn: Callable[[float, float], float], terms: Callable[[float, float], np.ndarray]):
        self._fn = fn
        self.terms = terms

    def __call__(self, c_on: float, c_off: float) -> float:
        return self._fn(c_on, c_off)


