"""The frame-to-frame consistency estimator of c (mEDI-style, the default): consecutive deblurred frames must
agree through the events between them, log B_k+1 - log D_k+1(c) = log B_k - log D_k(c) + c * E(f_k -> f_k+1);
minimise a robust sum of the residuals over a pixel subsample (coarse log grid, then golden section). Every
evaluation reuses the frames' level tables: events are not touched again."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

import edi_live.edi as edi
from edi_live.contrast.frames import FramePair
from edi_live.contrast.search import Cost, golden_section, grid_then_golden
from edi_live.contrast.vectors import dot


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
    separate_z: float = 3.0  # separate thresholds only when they beat one c by this many standard errors
    name: str = "consistency"
    needs_pair: bool = True
    needs_full_image: bool = False
    last_evaluations: int = field(default=0, init=False)

    def _problem(self, pairs: Sequence[FramePair]):
        """Sum of the pairs' robust residual costs, or None when no pair has enough informative pixels."""
        costs = [c for c in (self._cached_pair_problem(p) for p in pairs) if c is not None]
        if not costs:
            return None
        if len(costs) == 1:
            return costs[0]
        return Cost(lambda c_on, c_off: sum(fn(c_on, c_off) for fn in costs),
                     lambda c_on, c_off: np.concatenate([fn.terms(c_on, c_off) for fn in costs]))

    def _cached_pair_problem(self, pair: FramePair):
        key = ("consistency-v3", self.max_pixels, self.min_pixels, self.b_low, self.b_high, self.delta,
               self.spread_weight)
        if key not in pair.cache:
            pair.cache[key] = self._pair_problem(pair)
        return pair.cache[key]

    def _pair_problem(self, pair: FramePair):
        """Residual setup on a deterministic subsample; returns cost(c_on, c_off) or None."""
        prev, cur = pair.prev, pair.cur
        bp = prev.blurry.reshape(-1)
        bc = cur.blurry.reshape(-1)
        cand = edi.pair_candidates(prev.informative, cur.informative, bp, bc, self.b_low, self.b_high, pair.mask,
                                   pair.n_on, pair.n_off, prev.table.pixels, cur.table.pixels)
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
            rows, at = edi.rows_of(frame.table, cand, spread)  # `at`: where in cand, ascending
            parts.append((at, frame.table.take(rows)))
        # pixels that crossed many levels within an exposure carry more quantisation error in L(f)
        weight = 1.0 / (1.0 + self.spread_weight * spread)
        (row_p, sub_p), (row_c, sub_c) = parts  # row_*: where in cand each table row's pixel is
        delta2 = self.delta ** 2
        if edi.have_numba():  # fused kernel for the common single-c case: no temporaries per evaluation
            net = n_on - n_off

            def jit_cost(c: float, out: np.ndarray | None) -> float:
                return edi.consistency_cost(c, dlog_b, net, weight, delta2, sub_p, row_p, sub_c, row_c, out)

            def fast_cost(c_on: float, c_off: float) -> float:
                if c_on != c_off:
                    return float(np.sum(terms(c_on, c_off)))
                return jit_cost(c_on, None)

        def predict(c_on: float, c_off: float) -> np.ndarray:
            """Every pixel's predicted log B_cur - log B_prev (events between the frames and both divisors)."""
            pred = c_on * n_on - c_off * n_off
            if sub_c.n_active:
                pred[row_c] += edi.log_divisor(sub_c, c_on, c_off)
            if sub_p.n_active:
                pred[row_p] -= edi.log_divisor(sub_p, c_on, c_off)
            return pred

        def terms(c_on: float, c_off: float) -> np.ndarray:
            """Every pixel's weighted robust residual (the cost is their sum)."""
            if edi.have_numba() and c_on == c_off:
                out = np.empty(dlog_b.size)
                jit_cost(c_on, out)
                return out
            r = dlog_b - predict(c_on, c_off)
            return weight * np.sqrt(delta2 + r * r)

        cost = fast_cost if edi.have_numba() else (lambda c_on, c_off: float(np.sum(terms(c_on, c_off))))
        return Cost(cost, terms)

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
            # one c unless the data clearly separate them: (c_on, c_off) must beat (c, c) by separate_z standard
            # errors of the per-pixel cost difference
            z = self.compare(pairs, (c, c), [(c_on, c_off)])
            if z is None or z < self.separate_z:
                c_on = c_off = c
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
            var = max(dot(d, d) / n - (total / n) ** 2, 0.0)
            zs.append(total / (math.sqrt(n * var) + tiny))
        return max(zs) if best else min(zs)

    def misfit(self, cur, pairs, c):
        return self.fit_score(pairs, c)

    def still_misfit(self, cur, pairs, floor, cached):
        return self.compare(pairs, floor, [cached])

    def confirm_still(self, pairs, c, floor):
        return self.compare(pairs, c, [floor])


