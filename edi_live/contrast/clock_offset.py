"""The offset between the event clock and the APS exposure window, from two consecutive APS frames (the policy that
runs it is edi_live.clock_offset_policy; see docs/calibration.md).

With the exposure window off by d (event time = APS time + d), the events that explain a frame's blur are counted
in the wrong window and two frames stop agreeing through the events between them. Under EDI's model a pixel's
blurry value is its log-intensity base times the mean of exp(S(t)) over the exposure, S being the running signed
event sum (+c_on per ON event, -c_off per OFF event); so the consistency residual of a pair is
    r = log(B_k+1 - b) - log(B_k - b) - (log mean_{window k+1 + d} exp(S) - log mean_{window k + d} exp(S))
(the same r as with two level tables and the event counts between the mid-exposures: the counts cancel). Each
pixel's integral of exp(S) is piecewise linear in time, so it is built once per fit and read at the four window
ends for every candidate d. The robust cost (sum over a fixed pixel sample) is searched coarse to fine (1 ms grid,
then 250 µs around the best point) and the best point refined with a parabola.

EDI's piecewise-constant E(t) holds a level from one event to the next, while the log intensity it stands for
moves through that level continuously: it lags by about half the pixel's inter-event interval, and the fit
absorbs that lag (2.2 ms found on an ideal camera at 200 px/s). `midlevel_times` removes it first: each event's
level change is placed half-way back to the pixel's previous event of the same polarity (gaps capped), which is
where a steadily moving log intensity sits at the level's middle; an event with no such predecessor in the batch
(the stream's or the collection's start, an edge reaching a still pixel) is moved by half the gap to its successor
instead, and an event alone of its pixel and polarity by the cap (its gaps are longer than the batch's half).
Then the ideal camera gives ~0.1 ms and a 1.5 ms offset ~1.6 ms (medians over 11 pairs, 3000 pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from edi_live.contrast import _kernels_clock_offset
from edi_live.contrast.vectors import dot
from edi_live.edi import have_numba


@dataclass(frozen=True)
class FrameWindow:
    """One APS frame as the offset search needs it: its stated exposure (µs, APS clock), B on the 8-bit scale
    (float) and which pixels are informative."""

    exposure_start_us: int
    exposure_end_us: int
    blurry: np.ndarray
    informative: np.ndarray


def estimate_clock_offset(events: np.ndarray, prev: FrameWindow, cur: FrameWindow, sample: np.ndarray,
                          c: tuple[float, float], *, lag_share: float = 1.0, **options: Any) -> float | None:
    """d in µs (events late by d: event time = APS time + d) within +-max_offset_us, or None when the frames
    say nothing (too few usable pixels, a flat cost, or the best offset at an edge of the searched range).
    `events`: time-ordered; candidates whose windows the events do not cover are left out (a batch that starts at
    the first exposure cannot test events early); `complete_until_us`: the events are known to be complete up to
    then (default: the last event; a sparse stream's last event comes early). With midlevel_gap_us, the events'
    times are first moved as `midlevel_times(events, width, midlevel_gap_us)` would (on the used pixels only:
    cheaper). `sample`: (H, W) bool pixels to use, of which those with events near the windows count (at most
    max_pixels of them, evenly spread: the cost grows with them); `mask`: pixels whose events are ignored. With
    min_z, the best point must beat both points z_step_us away (those within the covered range) by min_z standard
    errors of the per-pixel cost difference (paired over pixels), else None: a shallow or noisy cost curve says
    nothing about the offset. The options and their defaults are clock_offset_fit's keywords."""
    return clock_offset_fit(events, prev, cur, sample, c, **options)(lag_share)


def clock_offset_fit(events: np.ndarray, prev: FrameWindow, cur: FrameWindow, sample: np.ndarray,
                     c: tuple[float, float], *, black_level: float = 0.0, mask: np.ndarray | None = None,
                     max_offset_us: int = 4000, step_us: int = 250, coarse_step_us: int = 1000,
                     midlevel_gap_us: int | None = None, complete_until_us: int | None = None,
                     max_pixels: int | None = None, b_low: float = 6.0, b_high: float = 250.0,
                     delta: float = 0.1, min_pixels: int = 30, min_z: float = 0.0,
                     z_step_us: int = 1000) -> Callable[[float], float | None]:
    """estimate_clock_offset's fit as a function of lag_share: the pixels, their events and the events' mid-level
    shifts do not depend on it and are taken once, for every share asked."""
    selection: list = []

    def select() -> tuple | None:
        h, w = sample.shape
        if events.size == 0:
            return None
        t = events["t"]
        d_lo = max(-max_offset_us, -((prev.exposure_start_us - int(t[0])) // step_us) * step_us)
        until = int(t[-1]) if complete_until_us is None else max(int(t[-1]), complete_until_us)
        d_hi = min(max_offset_us, ((until - cur.exposure_end_us) // step_us) * step_us)
        if d_hi - d_lo < 2 * step_us:
            return None  # the batch does not cover the windows
        bp = prev.blurry.reshape(-1) - black_level
        bc = cur.blurry.reshape(-1) - black_level
        use = sample.reshape(-1) & prev.informative.reshape(-1) & cur.informative.reshape(-1)
        use &= (bp >= b_low) & (bp <= b_high) & (bc >= b_low) & (bc <= b_high)
        if mask is not None:
            use &= ~mask.reshape(-1)
        lo, hi = prev.exposure_start_us + d_lo, cur.exposure_end_us + d_hi
        # pixels without an event near the windows cost the same at every offset: only pixels with events count
        with_events = np.zeros(h * w, bool)
        near = events[np.searchsorted(t, lo - (midlevel_gap_us or 0) // 2):np.searchsorted(t, hi, "right")]  # t ascends
        with_events[near["y"].astype(np.int64) * w + near["x"]] = True
        pixels = np.flatnonzero(use & with_events)
        if max_pixels is not None and pixels.size > max_pixels:
            pixels = pixels[np.linspace(0, pixels.size - 1, max_pixels).astype(np.int64)]
        if pixels.size < min_pixels:
            return None
        dlog_b = np.log(bc[pixels]) - np.log(bp[pixels])
        return d_lo, d_hi, lo, hi, dlog_b, _PixelEvents(events, pixels, w, midlevel_gap_us)

    def fit(lag_share: float = 1.0) -> float | None:
        if not selection:
            selection.append(select())
        if selection[0] is None:
            return None
        d_lo, d_hi, lo, hi, dlog_b, pixel_events = selection[0]
        sums = _ExposureSums(pixel_events, lo, hi, c, lag_share)
        ends = np.array([prev.exposure_start_us, prev.exposure_end_us, cur.exposure_start_us, cur.exposure_end_us])
        spans = (max(prev.exposure_end_us - prev.exposure_start_us, 1),
                 max(cur.exposure_end_us - cur.exposure_start_us, 1))
        cache: dict[int, np.ndarray] = {}

        def evaluate(ds) -> None:
            todo = np.array(sorted({int(d) for d in ds} - cache.keys()), np.int64)
            if todo.size:
                cache.update(zip(todo.tolist(), _terms(sums, ends, spans, todo, dlog_b, delta)))

        def cost(d: int) -> float:
            return float(cache[int(d)].sum())

        # a coarse grid over the covered range, then the fine grid around its best point
        evaluate(np.r_[np.arange(d_lo, d_hi, coarse_step_us), d_hi])
        best = min(cache, key=cost)
        fine = np.arange(max(d_lo, best - coarse_step_us), min(d_hi, best + coarse_step_us) + 1, step_us)
        evaluate(fine)
        i = int(min(range(fine.size), key=lambda j: cost(fine[j])))
        d_best = int(fine[i])
        if d_best in (d_lo, d_hi):
            # not a minimum: it may lie beyond what the events cover, or the cost only drifts across the range (a
            # noise-only scene drifts to +max_offset_us, and the z test below does not tell a drift from a minimum)
            return None
        if min_z > 0:
            sides = [d for d in (d_best - z_step_us, d_best + z_step_us) if d_lo <= d <= d_hi]
            evaluate(sides)
            zs = []
            for d in sides:
                diff = cache[d] - cache[d_best]
                n = diff.size
                var = max(dot(diff, diff) / n - (float(diff.sum()) / n) ** 2, 0.0)
                zs.append(float(diff.sum()) / (np.sqrt(n * var) + 1e-12))
            if not zs or min(zs) < min_z:
                return None
        costs = np.array([cost(d) for d in cache])
        if not np.isfinite(costs).all() or float(costs.max() - costs.min()) <= 1e-9 * max(cost(d_best), 1e-12):
            return None
        out = float(d_best)
        if 0 < i < fine.size - 1:
            c0, c1, c2 = cost(fine[i - 1]), cost(d_best), cost(fine[i + 1])
            if c0 - 2 * c1 + c2 > 0:
                out += 0.5 * step_us * (c0 - c2) / (c0 - 2 * c1 + c2)
        return out

    return fit


class _PixelEvents:
    """The events of `pixels` (each as its rank r in `pixels`, time t, polarity p) and, with midlevel_gap_us, how
    far midlevel_times moves each back (`shift`, taken when first asked)."""

    def __init__(self, events: np.ndarray, pixels: np.ndarray, width: int, midlevel_gap_us: int | None) -> None:
        rank = np.full(int(pixels.max()) + 1, -1, np.int64)
        rank[pixels] = np.arange(pixels.size)
        flat = np.minimum(events["y"].astype(np.int64) * width + events["x"], rank.size - 1)
        r = rank[flat]
        keep = r >= 0
        self.r, self.t, self.p = r[keep], events["t"][keep].astype(np.int64), events["p"][keep]
        self.n = pixels.size
        self.midlevel_gap_us = midlevel_gap_us
        self._shift: np.ndarray | None = None

    @property
    def shift(self) -> np.ndarray:
        if self._shift is None:
            self._shift = _midlevel_shift(self.r * 2 + self.p, self.t, self.midlevel_gap_us)
        return self._shift


# |S| beyond this says nothing a pair of 8-bit frames could confirm (their log ratio is at most log(250 / 6) = 3.7),
# while exp(S) of a stuck pixel (thousands of events of one polarity) overflowed and turned the pair's cost to NaN
_MAX_LEVEL = 30.0


class _ExposureSums:
    """Per pixel of `pixels`, the integral from `lo` of exp(S(t)) (S: the signed event sum since lo), read at any
    times in [lo, hi] by `at(q)` (q: the times, the same for every pixel). Piecewise linear between events."""

    def __init__(self, ev: _PixelEvents, lo: int, hi: int, c: tuple[float, float], lag_share: float = 1.0) -> None:
        r, t, p = ev.r, ev.t, ev.p
        if ev.midlevel_gap_us is not None and lag_share:
            shift = ev.shift
            t = t - (shift if lag_share == 1.0 else np.round(lag_share * shift).astype(np.int64))
        inside = (t >= lo) & (t <= hi)
        n = ev.n
        # each pixel starts with a mark at lo (no level change), so that every time has an event at or before it
        r = np.concatenate([np.arange(n, dtype=np.int64), r[inside]])
        t = np.concatenate([np.full(n, lo, np.int64), t[inside]])
        step = np.concatenate([np.zeros(n), np.where(p[inside], c[0], -c[1])])
        span = hi - lo + 2  # one key range per pixel
        key = r * span + (t - lo)
        order = np.argsort(key * 2 + (np.arange(key.size) >= n))  # by pixel, then time; a pixel's mark first
        self.key, r, t = key[order], r[order], t[order]
        first = np.ones(r.size, bool)
        first[1:] = r[1:] != r[:-1]
        level = np.clip(_grouped_cumsum(step[order], first), -_MAX_LEVEL, _MAX_LEVEL)  # S just after each event
        before = np.zeros(r.size)
        before[1:] = level[:-1]
        before[first] = 0.0
        t_before = np.empty_like(t)
        t_before[1:] = t[:-1]
        t_before[first] = lo
        integral = _grouped_cumsum(np.exp(before) * (t - t_before), first)  # up to each event
        self.slope = np.exp(level)
        self.intercept = integral - self.slope * (t - lo)  # the integral at q is intercept + slope * (q - lo)
        self.lo = lo
        self.n = n
        self.row_key = (np.arange(n, dtype=np.int64) * span - lo)[:, None]
        self.first = np.r_[np.flatnonzero(first), r.size]  # each pixel's entries (its mark first)

    def at(self, q: np.ndarray) -> np.ndarray:
        """(n_pixels, k): every pixel's integral at the times q (1-D, within [lo, hi])."""
        if have_numba():
            return _kernels_clock_offset.integrals_at(self.key, self.first, self.row_key[:, 0], q, self.intercept,
                                                      self.slope, self.lo)
        j = np.searchsorted(self.key, self.row_key + q, "right") - 1  # at or after the pixel's mark
        return self.intercept[j] + self.slope[j] * (q - self.lo)


def _grouped_cumsum(values: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Cumulative sums restarting at every True of `first`."""
    cs = np.cumsum(values)
    starts = np.flatnonzero(first)
    base = np.zeros(values.size)
    if starts.size:
        offsets = np.r_[0.0, cs[starts[1:] - 1]]
        base = np.repeat(offsets, np.diff(np.r_[starts, values.size]))
    return cs - base


def _terms(sums: _ExposureSums, ends: np.ndarray, spans: tuple[int, int], ds: np.ndarray, dlog_b: np.ndarray,
           delta: float) -> np.ndarray:
    """(len(ds), n_pixels) robust residuals, one row per offset (the cost is a row's sum). `ends`: the previous
    and current windows' (start, end)."""
    q = (ends[:, None] + ds[None, :]).reshape(-1)  # per pixel, in time order when the windows are apart
    g = sums.at(q).reshape(sums.n, 4, ds.size)
    mean_p = np.maximum(g[:, 1] - g[:, 0], 1e-9) / spans[0]
    mean_c = np.maximum(g[:, 3] - g[:, 2], 1e-9) / spans[1]
    r = dlog_b[:, None] - np.log(mean_c / mean_p)
    return np.sqrt(delta * delta + r * r).T


def _midlevel_shift(key: np.ndarray, t: np.ndarray, max_gap_us: int) -> np.ndarray:
    """How far midlevel_times moves each event back (µs). `key`: pixel and polarity; `t`: ascending times."""
    t0 = int(t[0]) if t.size else 0
    order = np.argsort(key * (int(t[-1]) - t0 + 1) + (t - t0)) if t.size else np.zeros(0, np.int64)  # key, time
    ts = t[order]
    k = key[order]
    same = k[1:] == k[:-1]
    gap = np.zeros(ts.size, np.int64)
    gap[1:][same] = np.diff(ts)[same]
    first = np.ones(ts.size, bool)
    first[1:] = ~same
    has_next = np.zeros(ts.size, bool)
    has_next[:-1] = same
    lone_first = first & has_next  # no predecessor here: the gap to its successor stands in
    gap[lone_first] = ts[np.flatnonzero(lone_first) + 1] - ts[lone_first]
    gap[first & ~has_next] = max_gap_us  # alone in the batch: both gaps are long (the batch spans > 2 caps)
    shift = np.empty_like(ts)
    shift[order] = np.minimum(gap, max_gap_us) // 2
    return shift


def pixel_polarity_key(events: np.ndarray, width: int) -> np.ndarray:
    """int64 per event: its pixel (row-major) and polarity in one number, unique per (x, y, p)."""
    return (events["y"].astype(np.int64) * width + events["x"]) * 2 + events["p"].astype(np.int64)


def midlevel_times(events: np.ndarray, width: int, max_gap_us: int = 10_000) -> np.ndarray:
    """A time-ordered copy of `events` with each event moved back by half the time since the previous event of the
    same pixel and polarity, or, for an event without one in `events`, half the time to its next one; each at most
    max_gap_us / 2, which is also the move of an event alone of its pixel and polarity in `events` (for batches
    longer than twice max_gap_us, such an event's gaps are both longer than that)."""
    key = pixel_polarity_key(events, width)
    out = events.copy()
    out["t"] = events["t"] - _midlevel_shift(key, events["t"].astype(np.int64), max_gap_us)
    return out[np.argsort(out["t"], kind="stable")]

