"""The APS black level from events and frames: plain functions on consecutive-frame pairs.

What identifies it: between two frames a pixel's events measure the log ratio of its linear intensity, c * N
(N the net event count), while the APS gives black + gain * I. Across pixels of different brightness that see the
same log change, log((B2 - b) / (B1 - b)) agrees with c * N only for the right b: a wrong b bends dark pixels'
ratios far more than bright ones', which no common c can undo. The fit uses "quiet" pixels only, with events
between the two exposures but none inside either, so that B1 and B2 are clean samples of the intensity and no
deblur model (with its step lag) enters; the residual is measured in events (r / c), so that the cost does not
shrink just because a large b stretches or a negative b compresses every log ratio. b is profiled on a grid of
whole DN with c fitted at each b (a robust regression of the log ratio on N); a flat profile is no information.

Only dark pixels carry the black level: a b wrong by e changes a log ratio by about e (1/(B1 - b) - 1/(B2 - b)),
which is small next to the count's quantisation error (up to +-c at each frame: a pixel's log level may sit anywhere in
its dead band of +-c around its reference, depending on its history) unless B - b is a few tens of DN. On a scene
without such pixels the profile is flat and its minimum is set by how that error happens to vary with brightness
(which a scene of few flat grey levels, such as blocks, does not average out): an estimate is only as good as its
support, the moving quiet pixels whose darker frame lies within `SUPPORT_DN` of it.

APS noise biases the minimum low (a dark pixel's log ratio gets noisier as b grows); black_level_noise.py measures
the noise and corrects an estimate for it.

A power-law APS response is not identified this way: it scales every log ratio alike and folds into c.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from edi_live.contrast import _kernels_black_level
from edi_live.contrast.frames import FramePair
from edi_live.contrast.vectors import dot
from edi_live.edi import have_numba

_MISS = 50.0  # the residual (in events) of a pixel that a black level b hides (at or below b + 1 DN)
_MISS_TERM = math.sqrt(0.25 + _MISS * _MISS) - 0.5  # its pseudo-Huber term (delta 0.5)
SUPPORT_DN = 30.0  # a moving quiet pixel supports an estimate b when its darker frame is at most this above b


@dataclass(frozen=True)
class QuietSamples:
    """Raw APS values (8-bit DN, black level not taken off) of quiet pixels in two frames and the net event count
    between them (flat float64 arrays of one length). `noise_diff` / `noise_level`: a sample of the APS noise
    (black_level_noise.neighbour_differences), one entry per pair of neighbouring event-free pixels."""

    b_prev: np.ndarray
    b_cur: np.ndarray
    net: np.ndarray
    noise_diff: np.ndarray = field(default_factory=lambda: np.zeros(0))
    noise_level: np.ndarray = field(default_factory=lambda: np.zeros(0))
    noise_step: np.ndarray = field(default_factory=lambda: np.zeros(0))  # how far apart the two pixels are

    @property
    def size(self) -> int:
        return int(self.net.size)

    @staticmethod
    def join(parts: "list[QuietSamples]") -> "QuietSamples":
        return QuietSamples(*(np.concatenate([getattr(p, k) for p in parts]) if parts else np.zeros(0)
                              for k in ("b_prev", "b_cur", "net", "noise_diff", "noise_level", "noise_step")))


@dataclass(frozen=True)
class BlackLevelFit:
    black_level: float  # DN, the grid point of the lowest cost
    c: float  # the c fitted with it (a nuisance here: quiet pixels are a biased selection for c)
    z: float  # how clearly it beats the grid points `z_step` DN either side, in standard errors (the weaker side)
    pixels: int
    moving: int = 0  # quiet pixels with events between the frames (N != 0)
    support: int = 0  # of those, the ones whose darker frame is within SUPPORT_DN of black_level


def quiet_samples(pair: FramePair, taken_off: float, *, b_low: float = 3.0, b_high: float = 250.0,
                  max_events: int = 3) -> QuietSamples:
    """The pair's quiet pixels: informative in both frames, no events inside either exposure (not in either frame's
    level table) and at most `max_events` net events between them. Pixels without events count too (leaving them
    out biased b upwards by ~13 DN on an ideal small scene: the |N| >= 1 selection favours ratios quantised up);
    larger counts are left out because they moved b by ~10 DN on the ideal 'demo' scene (blocks, no pixel near
    the black level: any change of the sample moves the minimum of a flat profile, see the module docstring),
    while the scenes with a true black level moved by at most 1 DN without them. `taken_off` is the black level
    already taken off the pair's frames (it is added back, so that samples from frames with different corrections
    pool)."""
    bp, bc, ok, taken_off = quiet_values(pair, taken_off, b_low, b_high)
    cand = np.flatnonzero(ok)
    net = pair.n_on[cand].astype(np.float64) - pair.n_off[cand].astype(np.float64)
    keep = np.abs(net) <= max_events
    cand, net = cand[keep], net[keep]
    return QuietSamples(bp[cand].astype(np.float64) + taken_off, bc[cand].astype(np.float64) + taken_off, net)


def pair_values(pair: FramePair, taken_off: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(B of the older frame, of the newer one, the pixels usable in both, what to add to B for the raw APS value):
    flat. With the frames' `raw` values (a black level `taken_off` was taken off both) B is the raw value and a
    pixel is usable where it is informative or only the black level hid it (above 0 and at most `taken_off`: the
    pixels that correct a black level set too high); clipped pixels (at 0, at the saturation) stay out either way.
    Without them, B as the deblur has it, black level taken off."""
    prev, cur = pair.prev, pair.cur
    ok = prev.informative.reshape(-1) & cur.informative.reshape(-1)
    if prev.raw is None or cur.raw is None:
        return prev.blurry.reshape(-1), cur.blurry.reshape(-1), ok, taken_off
    bp, bc = prev.raw.reshape(-1), cur.raw.reshape(-1)
    ok = ((prev.informative.reshape(-1) | ((bp > 0.0) & (bp <= taken_off)))
          & (cur.informative.reshape(-1) | ((bc > 0.0) & (bc <= taken_off))))
    return bp, bc, ok, 0.0


def quiet_values(pair: FramePair, taken_off: float, b_low: float,
                 b_high: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """pair_values, with `ok` narrowed to the pixels within [b_low, b_high] DN in both frames, outside the pair's
    mask and without events inside either exposure (not in either frame's level table)."""
    bp, bc, ok, taken_off = pair_values(pair, taken_off)
    ok &= (bp >= b_low) & (bp <= b_high) & (bc >= b_low) & (bc <= b_high)
    if pair.mask is not None:
        ok &= ~pair.mask
    for frame in (pair.prev, pair.cur):
        ok[frame.table.pixels[:frame.table.n_active]] = False
    return bp, bc, ok, taken_off


def black_level_terms(s: QuietSamples, b: float, c: float, delta: float = 0.5) -> np.ndarray:
    """Per-pixel robust residual (pseudo-Huber, in events) of log((B2 - b) / (B1 - b)) against c * N; pixels at or
    below b + 1 DN get the largest term (a b that hides a pixel explains it worst)."""
    d, ok = _log_ratios(s, b)
    r = np.full(s.size, _MISS)
    r[ok] = d[ok] / c - s.net[ok]
    return np.sqrt(delta * delta + r * r) - delta


def fit_c(s: QuietSamples, b: float, delta: float = 0.5, iterations: int = 5) -> float:
    """c for a given b: robust regression of the APS log ratio on the net event count (iteratively reweighted, no
    intercept). The regression runs this way round because the event count's quantisation is the noise of the log
    ratio given N; fitting N on the ratio (minimising the residual in events over c) inflates c by 50 % here."""
    d, ok = _log_ratios(s, b)
    n = np.where(ok, s.net, 0.0)
    nn = dot(n, n)
    if nn <= 0:
        return float("nan")
    c = dot(d, n) / nn
    for _ in range(iterations):
        if not c > 0:
            return float("nan")
        w = 1.0 / np.sqrt(1.0 + ((d - c * n) / (c * delta)) ** 2)
        c = dot(w * d, n) / max(dot(w * n, n), 1e-12)
    return c if c > 0 else float("nan")


def profile_point(s: QuietSamples, b: float, bound: float = math.inf) -> tuple[float, float]:
    """(c, cost) of the profile at black level b: fit_c, then the sum of black_level_terms (inf when c is
    undefined); one compiled pass per step with the kernels. A cost above `bound` may come back as inf (the
    kernel stops summing there)."""
    if have_numba():
        return _kernels_black_level.profile_point(s.b_prev, s.b_cur, s.net, float(b), 0.5, 5, _MISS, bound)
    c = fit_c(s, b)
    return c, (float(np.sum(black_level_terms(s, b, c))) if c == c else math.inf)


def grid_minimum(cost: Callable[[float], float], lo: int, hi: int) -> float:
    """The whole-DN b in [lo, hi] of the lowest cost as the profile is searched: every 4 DN, then every DN within
    3 of the best of those."""
    b0 = min((float(b) for b in range(lo, hi + 1, 4)), key=cost)
    return min((float(b) for b in range(int(max(lo, b0 - 3)), int(min(hi, b0 + 3)) + 1)), key=cost)


def profile_search(s: QuietSamples, lo: int, hi: int, cache: dict[float, tuple[float, float]]) -> float:
    """grid_minimum of the profile's cost: the same b, but a point whose cost must exceed the best so far is not
    summed to the end. The hidden pixels alone (darker frame at or below b + 1 DN) cost _MISS_TERM each, and
    every term is >= 0 (the margin covers the sums' rounding). `cache` (b -> profile_point) gets the points
    evaluated in full and is read first."""
    darker_all = np.minimum(s.b_prev, s.b_cur)
    best = [math.inf]

    def searched(b: float) -> float:
        if b in cache:
            cost = cache[b][1]
        elif _MISS_TERM * np.count_nonzero(darker_all <= b + 1.0) > best[0] * (1.0 + 1e-9):
            return math.inf
        else:
            c, cost = profile_point(s, b, best[0] * (1.0 + 1e-9))
            if math.isfinite(cost) or not c == c:  # exact (an unbounded sum, or c undefined): kept
                cache[b] = (c, cost)
        best[0] = min(best[0], cost)
        return cost

    return grid_minimum(searched, lo, hi)


def fit_black_level(s: QuietSamples, b_range: tuple[float, float] = (0.0, 40.0), *, z_step: float = 4.0,
                    min_pixels: int = 50) -> BlackLevelFit | None:
    """Profile the cost over whole-DN b in `b_range` (c fitted per b); None without enough moving pixels."""
    if int(np.count_nonzero(s.net)) < min_pixels:
        return None
    lo_b, hi_b = math.floor(b_range[0]), math.ceil(b_range[1])
    cache: dict[float, tuple[float, float]] = {}

    def at(b: float) -> tuple[float, float]:
        if b not in cache:
            cache[b] = profile_point(s, b)
        return cache[b]

    b_best = profile_search(s, lo_b, hi_b, cache)
    c_best = at(b_best)[0]
    if not math.isfinite(at(b_best)[1]):
        return None
    base = black_level_terms(s, b_best, c_best)
    zs = []
    for side in (b_best - z_step, b_best + z_step):
        if side < lo_b or side > hi_b or not math.isfinite(at(side)[1]):
            continue
        d = black_level_terms(s, side, at(side)[0]) - base  # > 0 where b_best explains the pixel better
        n = d.size
        var = max(dot(d, d) / n - (float(d.sum()) / n) ** 2, 0.0)
        zs.append(float(d.sum()) / (math.sqrt(n * var) + 1e-12))
    z = min(zs) if zs else 0.0
    moving = s.net != 0
    darker = np.minimum(s.b_prev[moving], s.b_cur[moving])
    support = int(np.count_nonzero(darker <= b_best + SUPPORT_DN))
    return BlackLevelFit(float(b_best), float(c_best), z, s.size, int(np.count_nonzero(moving)), support)


def _log_ratios(s: QuietSamples, b: float) -> tuple[np.ndarray, np.ndarray]:
    """log((B2 - b) / (B1 - b)) where both are above b + 1 DN (0 elsewhere), and that mask."""
    ok = (s.b_prev > b + 1.0) & (s.b_cur > b + 1.0)
    d = np.zeros(s.size)
    d[ok] = np.log((s.b_cur[ok] - b) / (s.b_prev[ok] - b))
    return d, ok
