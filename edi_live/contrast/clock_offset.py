"""The offset between the event clock and the APS exposure window, from two consecutive APS frames (not wired into
the node yet: a tested function, see docs/calibration.md).

With the exposure window off by d (event time = APS time + d), the events that explain a frame's blur are counted
in the wrong window and two frames stop agreeing through the events between them. `estimate_clock_offset` scores,
for each candidate d, the robust consistency residual
    r = log(B_k+1 - b) - log(B_k - b) - (c_on n_on - c_off n_off + log D_k+1 - log D_k)
on one fixed pixel sample (both frames' level tables rebuilt with the windows moved by d), and refines the best
grid point with a parabola.

EDI's piecewise-constant E(t) holds a level from one event to the next, while the log intensity it stands for
moves through that level continuously: it lags by about half the pixel's inter-event interval, and the fit
absorbs that lag (2.2 ms found on an ideal camera at 200 px/s). `midlevel_times` removes it first: each event's
level change is placed half-way back to the pixel's previous event of the same polarity (gaps capped), which is
where a steadily moving log intensity sits at the level's middle. Then the ideal camera gives ~0.2 ms and a
1.5 ms offset ~1.7 ms (medians over 8 pairs, c given).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE


@dataclass(frozen=True)
class FrameWindow:
    """One APS frame as the offset search needs it: its stated exposure (µs, APS clock), B on the 8-bit scale
    (float) and which pixels are informative."""

    exposure_start_us: int
    exposure_end_us: int
    blurry: np.ndarray
    informative: np.ndarray


def estimate_clock_offset(events: np.ndarray, prev: FrameWindow, cur: FrameWindow, sample: np.ndarray,
                          c: tuple[float, float], *, black_level: float = 0.0, mask: np.ndarray | None = None,
                          max_offset_us: int = 4000, step_us: int = 250, b_low: float = 6.0,
                          b_high: float = 250.0, delta: float = 0.1, min_pixels: int = 30,
                          min_z: float = 0.0, z_step_us: int = 1000) -> float | None:
    """d in µs (events late by d: event time = APS time + d) within +-max_offset_us, or None when the frames
    say nothing (too few usable pixels, or a flat cost). `events`: time-ordered, covering both exposures moved by
    up to max_offset_us; `sample`: (H, W) bool pixels to use; `mask`: pixels whose events are ignored. With min_z,
    the best grid point must beat both points z_step_us away by min_z standard errors of the per-pixel cost
    difference (paired over pixels), else None: a shallow or noisy cost curve says nothing about the offset."""
    h, w = sample.shape
    if events.size == 0:
        return None
    t = events["t"]
    if int(t[0]) > prev.exposure_start_us - max_offset_us or int(t[-1]) < cur.exposure_end_us + max_offset_us:
        return None  # the batch does not cover every candidate window
    bp = prev.blurry.reshape(-1) - black_level
    bc = cur.blurry.reshape(-1) - black_level
    use = sample.reshape(-1) & prev.informative.reshape(-1) & cur.informative.reshape(-1)
    use &= (bp >= b_low) & (bp <= b_high) & (bc >= b_low) & (bc <= b_high)
    if mask is not None:
        use &= ~mask.reshape(-1)
    pixels = np.flatnonzero(use)
    if pixels.size < min_pixels:
        return None
    keep = np.zeros(h * w, bool)
    keep[pixels] = True
    sub = edi.events_at_pixels(events, w, h, keep.reshape(h, w))
    if sub.size == 0:
        return None
    dlog_b = np.log(bc[pixels]) - np.log(bp[pixels])
    offsets = np.arange(-max_offset_us, max_offset_us + 1, step_us)
    terms = np.array([_terms(sub, prev, cur, int(d), pixels, dlog_b, c, w, h, delta) for d in offsets])
    costs = terms.sum(axis=1)
    i = int(np.argmin(costs))
    if min_z > 0:
        k = max(1, z_step_us // step_us)
        zs = []
        for j in (i - k, i + k):
            if 0 <= j < offsets.size:
                diff = terms[j] - terms[i]
                n = diff.size
                var = max(float(diff.dot(diff)) / n - (float(diff.sum()) / n) ** 2, 0.0)
                zs.append(float(diff.sum()) / (np.sqrt(n * var) + 1e-12))
        if not zs or min(zs) < min_z:
            return None
    spread = float(costs.max() - costs.min())
    if not np.isfinite(costs[i]) or spread <= 1e-9 * max(float(costs[i]), 1e-12):
        return None
    best = float(offsets[i])
    if 0 < i < offsets.size - 1:
        curve = costs[i - 1] - 2 * costs[i] + costs[i + 1]
        if curve > 0:
            best += 0.5 * step_us * (costs[i - 1] - costs[i + 1]) / curve
    return best


def _terms(events: np.ndarray, prev: FrameWindow, cur: FrameWindow, d: int, pixels: np.ndarray,
           dlog_b: np.ndarray, c: tuple[float, float], w: int, h: int, delta: float) -> np.ndarray:
    """Per-pixel robust residuals for the offset d (the cost is their sum)."""
    pred = np.zeros(pixels.size)
    f_prev = (prev.exposure_start_us + prev.exposure_end_us) // 2 + d
    f_cur = (cur.exposure_start_us + cur.exposure_end_us) // 2 + d
    for frame, sign in ((prev, -1.0), (cur, 1.0)):
        table = edi.build_level_table(events, w, h, frame.exposure_start_us + d, frame.exposure_end_us + d,
                                      segments=c[0] != c[1])
        if table.n_active:
            pos = np.searchsorted(pixels, table.pixels)
            pred[pos] += sign * edi.log_divisor(table, c[0], c[1])
    n_on, n_off = edi.signed_counts(events, w, h, t0=f_prev + 1, t1=f_cur)
    pred += c[0] * n_on[pixels] - c[1] * n_off[pixels]
    r = dlog_b - pred
    return np.sqrt(delta * delta + r * r)


def midlevel_times(events: np.ndarray, width: int, max_gap_us: int = 10_000) -> np.ndarray:
    """A time-ordered copy of `events` with each event moved back by half the time since the previous event of the
    same pixel and polarity (at most max_gap_us / 2; a pixel's first event stays)."""
    key = (events["y"].astype(np.int64) * width + events["x"]) * 2 + events["p"].astype(np.int64)
    order = np.lexsort((events["t"], key))
    t = events["t"][order].astype(np.int64)
    k = key[order]
    gap = np.zeros(t.size, np.int64)
    same = k[1:] == k[:-1]
    gap[1:][same] = np.diff(t)[same]
    out = events.copy()
    moved = np.empty_like(t)
    moved[order] = t - np.minimum(gap, max_gap_us) // 2
    out["t"] = moved
    return out[np.argsort(out["t"], kind="stable")]


def warm_up_kernels() -> None:
    """Run the fit once on a tiny synthetic pair (one and two thresholds), so that its numba kernels are compiled or
    loaded before a stream starts rather than at the node's first round, mid-stream."""
    w, h = 8, 6
    rng = np.random.default_rng(1)
    events = np.zeros(400, EVENT_DTYPE)
    events["t"] = np.sort(rng.integers(0, 60_000, events.size))
    events["x"] = rng.integers(0, w, events.size)
    events["y"] = rng.integers(0, h, events.size)
    events["p"] = rng.integers(0, 2, events.size).astype(bool)
    image = np.full((h, w), 100.0)
    frames = [FrameWindow(t0, t0 + 10_000, image, np.ones((h, w), bool)) for t0 in (10_000, 35_000)]
    for c in ((0.2, 0.2), (0.2, 0.15)):
        estimate_clock_offset(midlevel_times(events, w), *frames, np.ones((h, w), bool), c, min_pixels=1,
                              max_offset_us=2000, min_z=3.0)
