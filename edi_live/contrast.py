"""Contrast-threshold (c) estimators for EDI: a protocol, fixed c, the paper's energy, and frame-to-frame consistency.

Owns: choosing c for an APS frame from its level table (edi.LevelTable) and, for the consistency estimator, the
previous frame. Every c evaluation reuses the per-frame level tables (O(pixels x levels), events are not touched
again). Pure numpy/cv2, no state beyond the estimator's parameters.

- `FixedContrast`: c_on/c_off given by the user.
- `EnergyContrast` (Pan et al. 2019, Sec. 4.2): minimise TV(L) - lambda * xcorr(Sobel|L|, Sobel|M|) by golden-section
  search, M the time-decayed signed event map around f. Both terms are normalised by their value at L = B.
- `ConsistencyContrast` (mEDI-style, physically grounded): consecutive deblurred frames must agree through the events
  between them, log B_k+1 - log D_k+1(c) = log B_k - log D_k(c) + c * E(f_k -> f_k+1); minimise a robust sum of
  the residuals over a pixel subsample (coarse log grid, then golden section).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import cv2
import numpy as np

import edi_live.edi as edi

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


@dataclass
class FrameData:
    """One APS frame as the estimators see it: B (8-bit scale, float32), which pixels are informative, its
    level table, and the signed event map M around f (for the energy estimator; None when not needed)."""

    blurry: np.ndarray
    informative: np.ndarray
    table: edi.LevelTable
    event_map: np.ndarray | None = None


@dataclass
class FramePair:
    """Two consecutive frames and the ON/OFF event counts per pixel from f_prev to f_cur (flat int arrays)."""

    prev: FrameData
    cur: FrameData
    n_on: np.ndarray
    n_off: np.ndarray
    mask: np.ndarray | None = None  # flat bool: pixels to ignore (hot)
    # estimators may keep their per-pair setup here (a pair is immutable once built; it serves several frames)
    cache: dict = field(default_factory=dict, repr=False, compare=False)


class ContrastEstimator(Protocol):
    name: str
    needs_pair: bool
    separate: bool

    def estimate(self, cur: FrameData, pairs: Sequence[FramePair], c_init: tuple[float, float]) \
            -> tuple[float, float] | None:
        """(c_on, c_off) for `cur`, or None when the data say nothing about c (keep the current value).
        `pairs`: recent consecutive-frame pairs, newest last (empty for the first frame)."""
        ...

    def fits(self, cur: FrameData, pairs: Sequence[FramePair], c: tuple[float, float]) -> bool:
        """Cheap test (a few evaluations) that c is still near the optimum of this estimator's criterion."""
        ...


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


def _three_point_fit(fn: Callable[[float], float], c: float, step: float) -> bool:
    mid = fn(c)
    return mid <= min(fn(c * (1.0 - step)), fn(c * (1.0 + step)))


class _Cost:
    """cost(c_on, c_off) -> float, plus .terms(c_on, c_off) -> the per-pixel terms that sum to it."""

    __slots__ = ("_fn", "terms")

    def __init__(self, fn: Callable[[float, float], float], terms: Callable[[float, float], np.ndarray]):
        self._fn = fn
        self.terms = terms

    def __call__(self, c_on: float, c_off: float) -> float:
        return self._fn(c_on, c_off)


@dataclass
class FixedContrast:
    c_on: float
    c_off: float
    name: str = "fixed"
    needs_pair: bool = False
    separate: bool = True

    def estimate(self, cur, pairs, c_init):
        return self.c_on, self.c_off

    def fits(self, cur, pairs, c):
        return True


def event_map(events: np.ndarray, width: int, height: int, ref_t_us: int, t0: int, t1: int,
              tau_us: float) -> np.ndarray:
    """M(f) = sum over events in [t0, t1] of polarity * exp(-|t - f| / tau), (H, W) float32."""
    sel = events[(events["t"] >= t0) & (events["t"] <= t1)]
    sel = sel[(sel["x"] < width) & (sel["y"] < height)]
    w = np.exp(-np.abs(sel["t"] - ref_t_us) / max(tau_us, 1.0)) * np.where(sel["p"], 1.0, -1.0)
    idx = sel["y"].astype(np.int64) * width + sel["x"]
    return np.bincount(idx, weights=w, minlength=width * height).reshape(height, width).astype(np.float32)


def _grad_mag(img: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def _tv(img: np.ndarray) -> float:
    dx = np.abs(np.diff(img, axis=1)).sum()
    dy = np.abs(np.diff(img, axis=0)).sum()
    return float(dx + dy)


@dataclass
class EnergyContrast:
    """The paper's energy: TV(L)/TV(B) - lam * <|grad L|, |grad M|> / <|grad B|, |grad M|>, golden-section search."""

    lam: float = 1.0
    c_min: float = 0.03
    c_max: float = 1.0
    tol: float = 2e-3
    fit_step: float = 0.1
    name: str = "energy"
    needs_pair: bool = False
    separate: bool = False
    needs_full_image: bool = True

    def _energy_fn(self, cur: FrameData) -> Callable[[float], float] | None:
        if cur.event_map is None or cur.table.n_active == 0:
            return None
        em = _grad_mag(cur.event_map)
        b = np.maximum(cur.blurry, edi.DARK_FLOOR)
        tv_b = max(_tv(b), 1e-6)
        xc_b = max(float((_grad_mag(b) * em).sum()), 1e-6)

        def energy(c: float) -> float:
            lat = np.exp(edi.deblur_log(b, cur.table, c, informative=cur.informative))
            np.clip(lat, 0.0, 4 * 255.0, out=lat)
            return _tv(lat) / tv_b - self.lam * float((_grad_mag(lat) * em).sum()) / xc_b

        return energy

    def estimate(self, cur, pairs, c_init):
        fn = self._energy_fn(cur)
        if fn is None:
            return None
        c = golden_section(fn, self.c_min, self.c_max, tol=self.tol)[0]
        return c, c

    def fits(self, cur, pairs, c):
        fn = self._energy_fn(cur)
        return True if fn is None else _three_point_fit(fn, c[0], self.fit_step)


@dataclass
class ConsistencyContrast:
    """Frame-to-frame consistency through the events between two deblurred frames (needs the previous frame)."""

    c_min: float = 0.02
    c_max: float = 2.0
    tol: float = 4e-3
    n_grid: int = 6
    max_pixels: int = 1000
    min_pixels: int = 30
    b_low: float = 6.0  # 8-bit scale: darker pixels are dominated by read noise and quantisation
    b_high: float = 250.0
    delta: float = 0.1  # pseudo-Huber scale of the log residual
    fit_step: float = 0.1
    fit_z: float = 3.0  # the fit test fails when a neighbour c is better by this many standard errors
    info_step: float = 0.3
    info_z: float = 2.0  # an estimate that beats c*(1 -+ info_step) by fewer standard errors carries no information
    spread_weight: float = 0.5
    separate: bool = False
    name: str = "consistency"
    needs_pair: bool = True
    last_evaluations: int = field(default=0, init=False)

    def _problem(self, pairs: Sequence[FramePair]):
        """Sum of the pairs' robust residual costs, or None when no pair has enough informative pixels."""
        costs = [c for c in (self._cached_pair_problem(p) for p in pairs) if c is not None]
        if not costs:
            return None
        if len(costs) == 1:
            return costs[0]
        return _Cost(lambda c_on, c_off: sum(fn(c_on, c_off) for fn in costs),
                     lambda c_on, c_off: np.concatenate([fn.terms(c_on, c_off) for fn in costs]))

    def _cached_pair_problem(self, pair: FramePair):
        key = ("consistency-v2", self.max_pixels, self.min_pixels, self.b_low, self.b_high, self.delta,
               self.spread_weight)
        if key not in pair.cache:
            pair.cache[key] = self._pair_problem(pair)
        return pair.cache[key]

    def _pair_problem(self, pair: FramePair):
        """Residual setup on a deterministic subsample; returns cost(c_on, c_off) or None."""
        prev, cur = pair.prev, pair.cur
        bp = prev.blurry.reshape(-1)
        bc = cur.blurry.reshape(-1)
        if edi.have_numba():  # one pass instead of a dozen image-wide temporaries
            as_u8 = lambda a: np.ascontiguousarray(a, dtype=bool).reshape(-1).view(np.uint8)  # noqa: E731
            mask = as_u8(pair.mask) if pair.mask is not None else np.zeros(0, np.uint8)
            cand = edi._jit.pair_candidates(as_u8(prev.informative), as_u8(cur.informative), bp, bc,
                                            np.float32(self.b_low), np.float32(self.b_high), mask,
                                            pair.mask is not None, pair.n_on, pair.n_off, prev.table.pixels,
                                            cur.table.pixels)
        else:
            ok = prev.informative.reshape(-1) & cur.informative.reshape(-1)
            ok &= (bp >= self.b_low) & (bp <= self.b_high) & (bc >= self.b_low) & (bc <= self.b_high)
            if pair.mask is not None:
                ok &= ~pair.mask
            signal = (pair.n_on + pair.n_off) > 0
            signal[prev.table.pixels] = True
            signal[cur.table.pixels] = True
            cand = np.flatnonzero(ok & signal)
        if cand.size < self.min_pixels:
            return None
        if cand.size > self.max_pixels:
            cand = cand[np.linspace(0, cand.size - 1, self.max_pixels).astype(np.int64)]
        dlog_b = np.log(bc[cand].astype(np.float64)) - np.log(bp[cand].astype(np.float64))
        n_on = pair.n_on[cand].astype(np.float64)
        n_off = pair.n_off[cand].astype(np.float64)
        parts = []
        spread = np.zeros(cand.size)
        for frame in (prev, cur):
            tab = frame.table
            pos = np.searchsorted(tab.pixels, cand)
            pos = np.minimum(pos, max(tab.n_active - 1, 0))
            hit = (tab.pixels[pos] == cand) if tab.n_active else np.zeros(cand.size, bool)
            spread[hit] += np.diff(tab.lvl_start)[pos[hit]] - 1
            parts.append((hit, tab.take(pos[hit])))
        # pixels that crossed many levels within an exposure carry more quantisation error in L(f)
        weight = 1.0 / (1.0 + self.spread_weight * spread)
        (hit_p, sub_p), (hit_c, sub_c) = parts
        delta2 = self.delta ** 2
        if edi.have_numba():  # fused kernel for the common single-c case: no temporaries per evaluation
            jit = edi._jit
            net = n_on - n_off
            row_p = np.flatnonzero(hit_p)
            row_c = np.flatnonzero(hit_c)

            no_terms = np.zeros(0)

            def jit_cost(c: float, out: np.ndarray) -> float:
                return jit.consistency_cost(float(c), dlog_b, net, weight, delta2, sub_p.lvl_start, sub_p.lvl_min,
                                            sub_p.lvl_frac, row_p, sub_c.lvl_start, sub_c.lvl_min, sub_c.lvl_frac,
                                            row_c, edi.LEVEL_CAP, out)

            def fast_cost(c_on: float, c_off: float) -> float:
                if c_on != c_off:
                    return float(np.sum(terms(c_on, c_off)))
                return jit_cost(c_on, no_terms)

        def terms(c_on: float, c_off: float) -> np.ndarray:
            """Every pixel's weighted robust residual (the cost is their sum)."""
            if edi.have_numba() and c_on == c_off:
                out = np.empty(dlog_b.size)
                jit_cost(c_on, out)
                return out
            pred = c_on * n_on - c_off * n_off
            if sub_c.n_active:
                pred[hit_c] += edi.log_divisor(sub_c, c_on, c_off)
            if sub_p.n_active:
                pred[hit_p] -= edi.log_divisor(sub_p, c_on, c_off)
            r = dlog_b - pred
            return weight * np.sqrt(delta2 + r * r)

        cost = fast_cost if edi.have_numba() else (lambda c_on, c_off: float(np.sum(terms(c_on, c_off))))
        return _Cost(cost, terms)

    def estimate(self, cur, pairs, c_init):
        cost = self._problem(pairs)
        if cost is None:
            return None
        c, n = grid_then_golden(lambda c: cost(c, c), self.c_min, self.c_max, n_grid=self.n_grid, tol=self.tol)
        c_on = c_off = c
        if self.separate:
            for _ in range(2):  # coordinate descent on the two thresholds around the common value
                c_off, _, k1 = golden_section(lambda x: cost(c_on, x), 0.5 * c_off, 2.0 * c_off, tol=self.tol)
                c_on, _, k2 = golden_section(lambda x: cost(x, c_off), 0.5 * c_on, 2.0 * c_on, tol=self.tol)
                n += k1 + k2
        self.last_evaluations = n
        return c_on, c_off

    def fit_score(self, pairs: Sequence[FramePair], c: tuple[float, float]) -> float | None:
        """How clearly a neighbour c*(1 -+ fit_step) beats c, in standard errors of the cost difference (paired
        over pixels: z = sum(d) / (sqrt(n) * std(d)), d the per-pixel cost differences). The cost's own noise sets
        the scale, so a flat or noisy cost curve does not look like a misfit. None: the pairs say nothing."""
        ratio = c[1] / c[0]
        return self.compare(pairs, c, [(x, x * ratio) for x in (c[0] * (1 - self.fit_step),
                                                                 c[0] * (1 + self.fit_step))], best=True)

    def information(self, pairs: Sequence[FramePair], c: tuple[float, float]) -> float | None:
        """How clearly c beats both c*(1 -+ info_step), in standard errors (the weaker side): a small value means
        the cost curve is flat around c (few moving pixels, little contrast), so an estimate there carries no
        information about the sensor's threshold."""
        ratio = c[1] / c[0]
        alts = [(x, x * ratio) for x in (c[0] * (1 - self.info_step), c[0] * (1 + self.info_step))]
        z = self.compare(pairs, c, alts, best=False)
        return None if z is None else -z

    def compare(self, pairs: Sequence[FramePair], c: tuple[float, float], alternatives, *,
                best: bool = True) -> float | None:
        """z of each alternative against c: the cost decrease sum(d) over its standard error sqrt(n)*std(d)
        (> 0: the alternative fits better). Returns the largest (best=True) or smallest z; None without data."""
        cost = self._problem(pairs)
        if cost is None:
            return None
        base = cost.terms(*c)
        n = base.size
        tiny = 1e-9 * (float(base.sum()) + 1e-9)  # terms are >= 0; guards an exactly constant difference
        zs = []
        for alt in alternatives:
            d = base - cost.terms(*alt)
            total = float(d.sum())
            var = max(float(d.dot(d)) / n - (total / n) ** 2, 0.0)
            zs.append(total / (math.sqrt(n * var) + tiny))
        return max(zs) if best else min(zs)

    def fits(self, cur, pairs, c):
        z = self.fit_score(pairs, c)
        return z is None or z < self.fit_z


ESTIMATORS = {"consistency": ConsistencyContrast, "energy": EnergyContrast}
DEFAULT_ESTIMATOR = "consistency"


def make_estimator(name: str, **kwargs) -> ContrastEstimator:
    """Estimator by name ('consistency', 'energy'); kwargs go to its constructor."""
    try:
        cls = ESTIMATORS[name]
    except KeyError:
        raise ValueError(f"unknown c estimator {name!r} (choose from {sorted(ESTIMATORS)})") from None
    return cls(**kwargs)
