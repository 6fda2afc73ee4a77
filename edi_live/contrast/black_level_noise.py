"""The APS read noise as the black-level fit sees it, and the fit's correction for it (plain functions).

Why: the black-level profile (black_level.py) weighs dark pixels, whose log ratios carry the black level b, and
APS noise of sigma DN adds about sigma / (B - b) to such a ratio: the larger the b tried, the noisier the dark
pixels look, so the robust cost prefers a smaller b (10 DN was found as 7 with 1 DN RMS noise and as 0 with 2 DN).

What measures sigma without the scene's own change: the temporal difference D = B2 - B1 of a pixel without any
event (between the frames or inside either exposure) is noise plus a sub-threshold change of the scene, and that
change is smooth across neighbouring pixels (a moving texture shifts both by nearly the same amount), while read
noise is independent from pixel to pixel. So the difference of D between two such neighbours has variance
4 sigma^2 (sigma^2 here includes the 8-bit rounding, 1/12 DN^2) plus a small texture term, which grows with
brightness (the change is multiplicative): it is measured on the dark pairs, within SUPPORT_DN of the black level,
the pixels whose noise biases the fit.

The correction is SIMEX (simulation-extrapolation): refit with extra Gaussian noise of variance lambda * sigma^2
added to both frames (lambda = 1, 2; a few fixed-seed draws averaged), fit the estimates' trend in lambda with a
parabola and read it at lambda = -1, where the data would have no noise. It needs no model of how the cost reacts
to noise, only sigma; where sigma is only rounding (0.29 DN) it moves an estimate by a few tenths of a DN.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from edi_live.contrast.black_level import (QuietSamples, SUPPORT_DN, grid_minimum, profile_point, quiet_values,
                                          quiet_samples)
from edi_live.contrast.frames import FramePair

MIN_NOISE_PAIRS = 50  # neighbour pairs needed for a read-noise estimate
SIMEX_LAMBDAS = (1.0, 2.0)
SIMEX_DRAWS = 4
SIMEX_RANGE = (-20.0, 60.0)  # a noisy fit may put b below 0: the trend in lambda must not be cut off there
SIMEX_MAX_SAMPLES = 30_000  # ~9 profile searches each: ~40 ms at 10k samples, ~0.5 s at 100k


def neighbour_differences(pair: FramePair, taken_off: float, step: int = 1, b_low: float = 3.0,
                          b_high: float = 250.0, keep: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """(D(x) - D(x'), the brighter frame value of the two pixels) for every pair of pixels x, x' `step` apart in a
    row or a column that are informative in both frames, within [b_low, b_high] DN and without any event from the
    first exposure's start to the second's end; D = B2 - B1 (values raw, `taken_off` added back). Only the `keep`
    darkest pairs are returned."""
    w = pair.prev.blurry.shape[1]
    bp, bc, ok, taken_off = quiet_values(pair, taken_off, b_low, b_high)  # the raw values where there are any
    ok &= (pair.n_on == 0) & (pair.n_off == 0)
    idx = np.flatnonzero(ok[:-step])
    right = idx[ok[idx + step] & (idx % w < w - step)]
    idx = np.flatnonzero(ok[:-step * w])
    below = idx[ok[idx + step * w]]
    first = np.concatenate([right, below])
    second = np.concatenate([right + step, below + step * w])
    level = np.maximum(np.maximum(bp[first], bc[first]), np.maximum(bp[second], bc[second]))
    if first.size > keep:  # a still scene would pool every pixel: only the dark ones are used (read_noise_dn)
        darkest = np.argpartition(level, keep - 1)[:keep]
        first, second, level = first[darkest], second[darkest], level[darkest]
    diff = (bc[first].astype(np.float64) - bp[first]) - (bc[second].astype(np.float64) - bp[second])
    return diff, level.astype(np.float64) + taken_off


def read_noise_dn(s: QuietSamples, black_level: float) -> float | None:
    """The APS noise sigma (DN RMS, rounding included) on the neighbour pairs within SUPPORT_DN of the black level
    (the darkest MIN_NOISE_PAIRS pairs when fewer are there), the smaller of the values from pixels 1 and 2 apart
    (texture only adds to either; in a Bayer mosaic direct neighbours see different colours); None with fewer
    than MIN_NOISE_PAIRS pairs."""
    found = []
    for step in np.unique(s.noise_step):
        of_step = s.noise_step == step
        e, level = s.noise_diff[of_step], s.noise_level[of_step]
        if e.size < MIN_NOISE_PAIRS:
            continue
        near = level <= black_level + SUPPORT_DN
        if np.count_nonzero(near) < MIN_NOISE_PAIRS:
            near = level <= np.partition(level, MIN_NOISE_PAIRS - 1)[MIN_NOISE_PAIRS - 1]
        found.append(math.sqrt(_clipped_mean_square(e[near]) / 4.0))
    return min(found) if found else None


def _clipped_mean_square(x: np.ndarray, k: float = 3.0, iterations: int = 5) -> float:
    """Mean square of x after clipping at k RMS (iterated from a MAD start): an edge that moved between the
    frames in one of the two pixels is not noise. The 0.5 DN floor keeps integer data with a MAD of 0 usable."""
    s = 1.4826 * float(np.median(np.abs(x))) + 0.5
    for _ in range(iterations):
        keep = np.abs(x) <= k * s
        s = math.sqrt(float(np.mean(x[keep] ** 2))) + 1e-12
    return s * s


def profile_minimum(b_prev: np.ndarray, b_cur: np.ndarray, net: np.ndarray,
                    b_range: tuple[float, float] = SIMEX_RANGE) -> float:
    """The profile's minimum as black_level.fit_black_level searches it (every 4 DN, then every DN around the
    best), refined between whole DN by a parabola through the best point and its neighbours."""
    lo, hi = math.floor(b_range[0]), math.ceil(b_range[1])
    cache: dict[float, float] = {}
    s = QuietSamples(b_prev, b_cur, net)

    def cost(b: float) -> float:
        if b not in cache:
            cache[b] = profile_point(s, b)[1]
        return cache[b]

    best = grid_minimum(cost, lo, hi)
    if best <= lo or best >= hi:
        return best
    left, mid, right = cost(best - 1.0), cost(best), cost(best + 1.0)
    curvature = left - 2.0 * mid + right
    if not (math.isfinite(curvature) and curvature > 0):
        return best
    return best + 0.5 * (left - right) / curvature


def simex_black_level(s: QuietSamples, sigma: float, seed: int = 0) -> tuple[float, list[float]]:
    """(the noise-free extrapolation of the profile's minimum, the minima at lambda = 0, 1, 2) for APS noise
    `sigma`; the samples' |N| selection is the caller's (fit_black_level's)."""
    rng = np.random.default_rng(seed)
    s = _capped(s, SIMEX_MAX_SAMPLES, rng)
    b0 = profile_minimum(s.b_prev, s.b_cur, s.net)
    # added noise only lowers the minimum: search below b0 first (a third of the grid), the whole range if it
    # ends on the window's edge
    window = (max(SIMEX_RANGE[0], math.floor(b0) - 24.0), min(SIMEX_RANGE[1], math.ceil(b0) + 8.0))

    def noisy_minimum(extra: float) -> float:
        bp = s.b_prev + extra * rng.standard_normal(s.size)
        bc = s.b_cur + extra * rng.standard_normal(s.size)
        b = profile_minimum(bp, bc, s.net, window)
        at_edge = (b <= window[0] and window[0] > SIMEX_RANGE[0]) or (b >= window[1] and window[1] < SIMEX_RANGE[1])
        return profile_minimum(bp, bc, s.net) if at_edge else b

    xs, ys = [0.0], [b0]
    for lam in SIMEX_LAMBDAS:
        xs.append(lam)
        ys.append(float(np.mean([noisy_minimum(math.sqrt(lam) * sigma) for _ in range(SIMEX_DRAWS)])))
    return float(np.polyval(np.polyfit(xs, ys, 2), -1.0)), ys


def _capped(s: QuietSamples, cap: int, rng: np.random.Generator) -> QuietSamples:
    """At most `cap` samples: every moving one (they carry the black level) and a random share of the others."""
    if s.size <= cap:
        return s
    moving = np.flatnonzero(s.net != 0)
    still = np.flatnonzero(s.net == 0)
    keep = np.sort(np.concatenate([moving, rng.choice(still, max(0, min(still.size, cap - moving.size)),
                                                      replace=False)]))
    return QuietSamples(s.b_prev[keep], s.b_cur[keep], s.net[keep])


def samples_with_noise(pair: FramePair, taken_off: float) -> QuietSamples:
    """black_level.quiet_samples of the pair with its neighbour_differences 1 and 2 pixels apart attached."""
    parts = [neighbour_differences(pair, taken_off, step) for step in (1, 2)]
    return dataclasses.replace(quiet_samples(pair, taken_off), noise_diff=np.concatenate([d for d, _ in parts]),
                               noise_level=np.concatenate([v for _, v in parts]),
                               noise_step=np.repeat([1.0, 2.0], [d.size for d, _ in parts]))


def noise_corrected(s: QuietSamples, black_level: float) -> tuple[float, float | None]:
    """(black level corrected for the APS noise, the noise sigma in DN); the estimate unchanged (and None) when
    the samples do not measure the noise."""
    sigma = read_noise_dn(s, black_level)
    if sigma is None:
        return black_level, None
    return simex_black_level(s, sigma)[0], sigma
