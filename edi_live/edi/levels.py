"""The per-exposure level table and the exact normalised double integral log D(c) evaluated from it.

`build_level_table` collects, per active pixel, the time fraction spent at each event state during one exposure
in O(events + pixels); `log_divisor` then gives log D for any (c_on, c_off) in O(active pixels x levels) without
touching the events again (see the package docstring for the model).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edi_live.edi import _backend, _kernels_levels
from edi_live.edi._backend import LEVEL_CAP
from edi_live.edi.selection import select, window


@dataclass(frozen=True, slots=True)
class LevelTable:
    """Per active pixel: the time fraction spent at each event state during one exposure.

    Segment arrays (one entry per constant piece, grouped by pixel, `seg_start` offsets) keep ON and OFF counts
    apart for separate thresholds. Level arrays (net count n_on - n_off, from `lvl_min` upwards, `lvl_start`
    offsets) are the compact form used when c_on == c_off. Fractions are dwell / T and sum to 1 per pixel.
    """

    width: int
    height: int
    exposure_start_us: int
    exposure_end_us: int
    ref_t_us: int
    pixels: np.ndarray  # (P,) int64 flat pixel index y*width + x, ascending
    seg_start: np.ndarray  # (P+1,) int64
    seg_on: np.ndarray  # (S,) int32
    seg_off: np.ndarray  # (S,) int32
    seg_frac: np.ndarray  # (S,) float64
    lvl_start: np.ndarray  # (P+1,) int64
    lvl_min: np.ndarray  # (P,) int32
    lvl_frac: np.ndarray  # (L,) float64
    n_events: int

    @property
    def exposure_us(self) -> int:
        return self.exposure_end_us - self.exposure_start_us

    @property
    def n_active(self) -> int:
        return int(self.pixels.size)

    @property
    def n_levels(self) -> int:
        return int(self.lvl_frac.size)

    def take(self, rows: np.ndarray) -> "LevelTable":
        """The table restricted to the active-pixel rows `rows` (ascending), e.g. a subsample for c search."""
        rows = np.asarray(rows, dtype=np.int64)
        if self.seg_frac.size == 0:  # built without segments: nothing to take there
            seg_idx, seg_start = np.zeros(0, np.int64), np.zeros(rows.size + 1, np.int64)
        else:
            seg_idx, seg_start = _ragged_take(self.seg_start, rows)
        lvl_idx, lvl_start = _ragged_take(self.lvl_start, rows)
        return LevelTable(
            self.width, self.height, self.exposure_start_us, self.exposure_end_us, self.ref_t_us,
            self.pixels[rows], seg_start, self.seg_on[seg_idx], self.seg_off[seg_idx], self.seg_frac[seg_idx],
            lvl_start, self.lvl_min[rows], self.lvl_frac[lvl_idx], self.n_events,
        )


def rows_of(table: LevelTable, pixels: np.ndarray, spread: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, at): the table rows of those of `pixels` (flat indices, ascending) that are active in the table, and
    their positions in `pixels` (ascending). Adds each such pixel's number of levels - 1 to `spread[at]` (float64,
    pixels' size)."""
    pixels = np.asarray(pixels, dtype=np.int64)
    if _backend.have_numba():
        return _kernels_levels.rows_of(table.pixels, table.lvl_start, pixels, spread)
    if table.n_active == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pos = np.minimum(np.searchsorted(table.pixels, pixels), table.n_active - 1)
    at = np.flatnonzero(table.pixels[pos] == pixels)
    rows = pos[at]
    spread[at] += np.diff(table.lvl_start)[rows] - 1
    return rows, at


def _ragged_take(start: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if _backend.have_numba():
        return _kernels_levels.ragged_take(start, rows)
    lengths = start[rows + 1] - start[rows]
    new_start = np.zeros(rows.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=new_start[1:])
    total = int(new_start[-1])
    # element k of row r maps to start[rows[r]] + (k - new_start[r])
    owner = np.repeat(np.arange(rows.size), lengths)
    idx = np.arange(total, dtype=np.int64) - new_start[owner] + start[rows][owner]
    return idx, new_start


def empty_table(width: int, height: int, ts: int, te: int, f: int) -> LevelTable:
    z64 = np.zeros(1, dtype=np.int64)
    e = np.zeros(0, dtype=np.int64)
    return LevelTable(width, height, ts, te, f, e, z64, e.astype(np.int32), e.astype(np.int32),
                      e.astype(np.float64), z64.copy(), e.astype(np.int32), e.astype(np.float64), 0)


def build_level_table(events: np.ndarray, width: int, height: int, exposure_start_us: int, exposure_end_us: int,
                      ref_t_us: int | None = None, *, mask: np.ndarray | None = None,
                      segments: bool = True, event_counts: np.ndarray | None = None) -> LevelTable:
    """Dwell-time table of one exposure, O(events + pixels). `events` time-ordered; those outside the
    exposure are ignored; `mask` (H, W) bool marks pixels whose events are ignored (hot pixels).

    ref_t_us defaults to mid-exposure and is clamped into the exposure. `segments=False` skips the ON/OFF
    segment arrays (faster; the table then serves only c_on == c_off). `event_counts` (flat int64, H*W), if
    given, gets every in-range event of the exposure added, masked or not (for hot-pixel statistics).
    """
    ts, te = int(exposure_start_us), int(exposure_end_us)
    if te < ts:
        raise ValueError(f"exposure ends before it starts (got {ts}..{te} µs)")
    f = (ts + te) // 2 if ref_t_us is None else min(max(int(ref_t_us), ts), te)
    if te == ts:
        return empty_table(width, height, ts, te, f)
    if _backend.have_numba():
        ev = window(events, ts, te)
        m, use_m = _backend.mask_arg(mask)
        cnt = _backend.NO_COUNTS if event_counts is None else event_counts
        parts = _kernels_levels.build_table(ev["t"], ev["x"], ev["y"], ev["p"], width, height, m, use_m, ts, te, f, segments,
                                 cnt, event_counts is not None)
        *arrays, n_events = parts
        if n_events == 0:
            return empty_table(width, height, ts, te, f)
        return LevelTable(width, height, ts, te, f, *arrays, int(n_events))
    if event_counts is not None:
        idx_all, _, _ = select(events, width, height, ts, te, None)
        event_counts += np.bincount(idx_all, minlength=width * height)
    idx, t, p = select(events, width, height, ts, te, mask)
    if idx.size == 0:
        return empty_table(width, height, ts, te, f)
    parts = _build_numpy(idx, t, p, ts, te, f, width * height)
    return LevelTable(width, height, ts, te, f, *parts, int(idx.size))


def _stable_argsort_pixels(idx: np.ndarray, npix: int) -> np.ndarray:
    # numpy's stable sort is a radix sort for 16-bit keys: two LSD passes beat one comparison sort
    if npix <= 1 << 16:
        return np.argsort(idx.astype(np.uint16), kind="stable")
    low = np.argsort((idx & 0xFFFF).astype(np.uint16), kind="stable")
    high = np.argsort((idx[low] >> 16).astype(np.uint16), kind="stable")
    return low[high]


def _build_numpy(idx, t, p, ts, te, f, npix):
    order = _stable_argsort_pixels(idx, npix)
    pix = idx[order]
    tt = t[order].astype(np.int64)
    on = p[order].astype(np.int32)
    n = pix.size
    first = np.flatnonzero(np.r_[True, pix[1:] != pix[:-1]])  # start of each pixel group
    pixels = pix[first]
    n_act = first.size
    counts = np.diff(np.r_[first, n])
    group = np.repeat(np.arange(n_act), counts)
    # inclusive per-pixel running counts of ON and OFF events
    c_on = np.cumsum(on)
    c_off = np.arange(1, n + 1, dtype=np.int64) - c_on
    base_on = (c_on[first] - on[first])
    base_off = (c_off[first] - (1 - on[first]))
    c_on = c_on - base_on[group]
    c_off = c_off - base_off[group]
    before = tt <= f
    j_on = np.add.reduceat((before & (on == 1)).astype(np.int64), first)
    j_off = np.add.reduceat((before & (on == 0)).astype(np.int64), first)
    # segments: one leading segment per pixel, then one after each event
    s_total = n + n_act
    ev_pos = np.arange(n) + group + 1
    lead_pos = first + np.arange(n_act)
    seg_on = np.empty(s_total, dtype=np.int32)
    seg_off = np.empty(s_total, dtype=np.int32)
    dwell = np.empty(s_total, dtype=np.float64)
    seg_on[lead_pos] = -j_on
    seg_off[lead_pos] = -j_off
    seg_on[ev_pos] = c_on - j_on[group]
    seg_off[ev_pos] = c_off - j_off[group]
    nxt = np.empty(n, dtype=np.int64)
    nxt[:-1] = tt[1:]
    nxt[-1] = te
    last = np.r_[first[1:] - 1, n - 1]
    nxt[last] = te
    dwell[lead_pos] = tt[first] - ts
    dwell[ev_pos] = nxt - tt
    seg_frac = dwell / float(te - ts)
    seg_start = np.r_[lead_pos, s_total].astype(np.int64)
    # compact net levels
    net = seg_on.astype(np.int64) - seg_off
    lvl_min = np.minimum.reduceat(net, seg_start[:-1])
    lvl_max = np.maximum.reduceat(net, seg_start[:-1])
    widths = lvl_max - lvl_min + 1
    lvl_start = np.zeros(n_act + 1, dtype=np.int64)
    np.cumsum(widths, out=lvl_start[1:])
    seg_group = np.repeat(np.arange(n_act), counts + 1)
    slot = lvl_start[seg_group] + (net - lvl_min[seg_group])
    lvl_frac = np.bincount(slot, weights=seg_frac, minlength=int(lvl_start[-1]))
    return (pixels.astype(np.int64), seg_start, seg_on, seg_off, seg_frac, lvl_start,
            lvl_min.astype(np.int32), lvl_frac)


def log_divisor(table: LevelTable, c_on: float, c_off: float | None = None) -> np.ndarray:
    """log D per active pixel (shape (P,), float64): log of (1/T) * integral of exp(c*E(t)) over the exposure.

    Exact; O(levels) when c_on == c_off, O(segments) otherwise; finite for any number of events.
    """
    c_off = c_on if c_off is None else c_off
    if table.n_active == 0:
        return np.zeros(0, dtype=np.float64)
    c_on = float(c_on)
    c_off = float(c_off)
    if c_on == c_off:
        if _backend.have_numba():
            return _kernels_levels.log_divisor_levels(table.lvl_start, table.lvl_min, table.lvl_frac, c_on, LEVEL_CAP)
        return _log_divisor_levels_numpy(table, c_on)
    if table.seg_frac.size == 0:
        raise ValueError("this level table was built without segments; build it with segments=True for c_on != c_off")
    if _backend.have_numba():
        return _kernels_levels.log_divisor_segments(table.seg_start, table.seg_on, table.seg_off, table.seg_frac, c_on, c_off)
    return _log_divisor_segments_numpy(table, c_on, c_off)


def _log_divisor_levels_numpy(table: LevelTable, c: float) -> np.ndarray:
    start = table.lvl_start
    widths = np.diff(start)
    cap = min(int(widths.max()), LEVEL_CAP)
    ztab = np.exp(c * np.arange(cap, dtype=np.float64))
    owner = np.repeat(np.arange(widths.size), widths)
    j = np.arange(start[-1], dtype=np.int64) - start[owner]
    out = np.empty(widths.size, dtype=np.float64)
    narrow = widths <= cap
    if narrow.all():
        sums = np.add.reduceat(table.lvl_frac * ztab[j], start[:-1])
        return c * table.lvl_min + np.log(sums)
    jj = np.minimum(j, cap - 1)
    sums = np.add.reduceat(table.lvl_frac * ztab[jj], start[:-1])
    out[narrow] = c * table.lvl_min[narrow] + np.log(sums[narrow])
    for r in np.flatnonzero(~narrow):  # rare: hot pixels with hundreds of net events; log-sum-exp
        w = table.lvl_frac[start[r]:start[r + 1]]
        a = c * np.arange(w.size)
        nz = w > 0
        m = a[nz].max()
        out[r] = c * table.lvl_min[r] + m + np.log(np.sum(w[nz] * np.exp(a[nz] - m)))
    return out


def _log_divisor_segments_numpy(table: LevelTable, c_on: float, c_off: float) -> np.ndarray:
    start = table.seg_start[:-1]
    a = c_on * table.seg_on - c_off * table.seg_off.astype(np.float64)
    a_masked = np.where(table.seg_frac > 0, a, -np.inf)
    m = np.maximum.reduceat(a_masked, start)
    m = np.where(np.isfinite(m), m, 0.0)  # a pixel whose every segment has zero dwell cannot occur (sum = 1)
    counts = np.diff(table.seg_start)
    s = np.add.reduceat(table.seg_frac * np.exp(np.minimum(a_masked - np.repeat(m, counts), 0.0)), start)
    return m + np.log(s)


