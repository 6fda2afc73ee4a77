"""The Event-based Double Integral (EDI, Pan et al. CVPR 2019) as pure functions on numpy arrays.

Owns: the per-frame level table, the exact normalised double integral, deblurring one APS frame, and latent
propagation. No I/O, no threads, no state beyond the arguments. Times are int64 µs; intensities are float on
the 8-bit APS scale (0..255, linear).

Model, per pixel, for an APS frame with exposure [ts, te], T = te - ts, and reference time f in [ts, te]:

    log L(t) - log L(f) = c_on * n_on(f->t) - c_off * n_off(f->t)        (n counts signed: negative for t < f)
    B = (1/T) * integral_ts^te L(t) dt = L(f) * D(c),   D(c) = (1/T) * integral exp(c_on*n_on - c_off*n_off) dt

E(t) is piecewise constant between a pixel's events, so D(c) is an exact finite sum over the states the pixel
visited, weighted by the time spent there:  D(c) = sum_k (dwell_k / T) * exp(c_on*on_k - c_off*off_k).
`build_level_table` collects those dwell times once per frame in O(events); `log_divisor` then evaluates log D for
any (c_on, c_off) in O(active pixels x levels) without touching events again. Pixels without events in the
exposure have D = 1 and are never computed.

Window convention (half-open in the usual sense, closed at the exposure ends):

    ts ------[seg 0)----- e1 -----[seg 1)----- e2 ---- ... ---- ek -----[seg k]----- te
    an event at exactly f counts as "before f" (the segment that contains f has level 0).
"""

from __future__ import annotations

import bisect
import os
from dataclasses import dataclass

import numpy as np

from edi_live.datatypes import EVENT_DTYPE

try:  # optional compiled kernels; every function below has a numpy fallback
    if os.environ.get("EDI_LIVE_NO_NUMBA"):
        raise ImportError("disabled by EDI_LIVE_NO_NUMBA")
    import edi_live._jit as _jit
except ImportError:  # pragma: no cover - depends on the environment
    _jit = None

LEVEL_CAP = 256
"""Pixels whose net level range is wider than this are evaluated with a per-entry log-sum-exp (no lookup table)."""
LOG_MIN = -30.0
LOG_MAX = 30.0
"""Bounds of the log-intensity state (8-bit scale): keeps every exp() finite whatever the events say."""
DARK_FLOOR = 0.25
"""B values below this (8-bit scale) are treated as this, so log B is finite."""


def have_numba() -> bool:
    return _jit is not None


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


def _ragged_take(start: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    lengths = start[rows + 1] - start[rows]
    new_start = np.zeros(rows.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=new_start[1:])
    total = int(new_start[-1])
    # element k of row r maps to start[rows[r]] + (k - new_start[r])
    owner = np.repeat(np.arange(rows.size), lengths)
    idx = np.arange(total, dtype=np.int64) - new_start[owner] + start[rows][owner]
    return idx, new_start


def flat_index(events: np.ndarray, width: int) -> np.ndarray:
    return events["y"].astype(np.int64) * width + events["x"].astype(np.int64)


def _has_event_fields(events: np.ndarray) -> bool:
    names = events.dtype.names or ()
    return all(n in names for n in ("t", "x", "y", "p"))


def _window(events: np.ndarray, t0: int | None, t1: int | None) -> np.ndarray:
    """The time-ordered events with t0 <= t <= t1, as a view (binary search, no copy)."""
    if events.dtype != EVENT_DTYPE and not _has_event_fields(events):
        raise TypeError(f"events must be a structured array of EVENT_DTYPE (got {events.dtype})")
    t = events["t"]
    lo = 0 if t0 is None else time_index(t, t0, "left")
    hi = t.size if t1 is None else time_index(t, t1, "right")
    return events[lo:hi]


def time_index(t: np.ndarray, value: int, side: str = "left") -> int:
    """Binary search on the (strided) `events["t"]` view. Unlike np.searchsorted, a key of another dtype (float,
    Python int beyond int64) never makes numpy cast the whole array first."""
    find = bisect.bisect_left if side == "left" else bisect.bisect_right
    return find(t, value)


_NO_MASK = np.zeros(0, dtype=np.uint8)
_NO_COUNTS = np.zeros(0, dtype=np.int64)


def _mask_arg(mask: np.ndarray | None) -> tuple[np.ndarray, bool]:
    if mask is None:
        return _NO_MASK, False
    return np.ascontiguousarray(mask, dtype=bool).reshape(-1).view(np.uint8), True


def _select(events: np.ndarray, width: int, height: int, t0: int | None, t1: int | None,
            mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Events with t0 <= t <= t1 (time-ordered input), in bounds and not masked: (flat idx, t, p)."""
    if events.dtype != EVENT_DTYPE and not _has_event_fields(events):
        raise TypeError(f"events must be a structured array of EVENT_DTYPE (got {events.dtype})")
    t = events["t"]
    lo = 0 if t0 is None else time_index(t, t0, "left")
    hi = t.size if t1 is None else time_index(t, t1, "right")
    ev = events[lo:hi]
    x = ev["x"]
    y = ev["y"]
    idx = y.astype(np.int64) * width + x
    keep = (x < width) & (y < height)
    if mask is not None:
        keep &= ~mask.reshape(-1)[np.minimum(idx, width * height - 1)]
    if keep.all():
        return idx, ev["t"], ev["p"]
    return idx[keep], ev["t"][keep], ev["p"][keep]


def events_at_pixels(events: np.ndarray, width: int, height: int, pixels: np.ndarray, t0: int | None = None,
                     t1: int | None = None) -> np.ndarray:
    """The events with t0 <= t <= t1 (time-ordered input) at the pixels marked in `pixels` ((H, W) bool), in
    order: a small copy, so that a per-frame table of a pixel sample costs O(sample events), not O(events)."""
    ev = _window(events, t0, t1)
    keep = np.ascontiguousarray(pixels, dtype=bool).reshape(-1)
    if _jit is not None:
        return ev[_jit.select_pixels(ev["x"], ev["y"], width, height, keep.view(np.uint8))]
    x = ev["x"]
    y = ev["y"]
    inside = (x < width) & (y < height)
    idx = y.astype(np.int64) * width + x
    return ev[inside & keep[np.where(inside, idx, 0)]]


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
    if _jit is not None:
        ev = _window(events, ts, te)
        m, use_m = _mask_arg(mask)
        cnt = _NO_COUNTS if event_counts is None else event_counts
        parts = _jit.build_table(ev["t"], ev["x"], ev["y"], ev["p"], width, height, m, use_m, ts, te, f, segments,
                                 cnt, event_counts is not None)
        *arrays, n_events = parts
        if n_events == 0:
            return empty_table(width, height, ts, te, f)
        return LevelTable(width, height, ts, te, f, *arrays, int(n_events))
    if event_counts is not None:
        idx_all, _, _ = _select(events, width, height, ts, te, None)
        event_counts += np.bincount(idx_all, minlength=width * height)
    idx, t, p = _select(events, width, height, ts, te, mask)
    if idx.size == 0:
        return empty_table(width, height, ts, te, f)
    parts = _build_numpy(idx, t, p, ts, te, f, width * height)
    return LevelTable(width, height, ts, te, f, *parts, int(idx.size))


def log_divisor_events(events: np.ndarray, width: int, height: int, exposure_start_us: int, exposure_end_us: int,
                       ref_t_us: int | None, c_on: float, c_off: float | None = None, *,
                       mask: np.ndarray | None = None,
                       event_counts: np.ndarray | None = None,
                       counts_after_f: tuple[np.ndarray, np.ndarray] | None = None) \
        -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(active pixels, log D, exponent change f->te or None) for ONE c straight from the events.

    Same log D as log_divisor(build_level_table(...)) but, for c_on == c_off with numba, a single pass without
    sorting, which also yields c * E(f -> te) per active pixel (so the latent image at te costs O(pixels)).
    Pixel order is unspecified. `mask`/`event_counts` as in build_level_table. `counts_after_f` (flat int64
    n_on, n_off): when the single pass runs (the third result is not None), it adds the ON/OFF counts of the
    unmasked events in (f, te] to them, which saves the caller a second pass; otherwise they are left alone.
    """
    c_off = c_on if c_off is None else c_off
    ts, te = int(exposure_start_us), int(exposure_end_us)
    if te < ts:
        raise ValueError(f"exposure ends before it starts (got {ts}..{te} µs)")
    f = (ts + te) // 2 if ref_t_us is None else min(max(int(ref_t_us), ts), te)
    if _jit is not None and c_on == c_off and 0 < te - ts < 2**24:  # float32 times in the pass are exact
        ev = _window(events, ts, te)
        m, use_m = _mask_arg(mask)
        cnt = _NO_COUNTS if event_counts is None else event_counts
        acc_on, acc_off = counts_after_f if counts_after_f is not None else (_NO_COUNTS, _NO_COUNTS)
        npix = width * height
        return _jit.divisor_stream(ev["t"], ev["x"], ev["y"], ev["p"], width, height, m, use_m, ts, te, f,
                                   float(c_on), cnt, event_counts is not None, np.empty(npix, _jit.DIVISOR_STATE),
                                   np.zeros(npix, np.uint8), acc_on, acc_off, counts_after_f is not None)
    table = build_level_table(events, width, height, ts, te, f, mask=mask, segments=c_on != c_off,
                              event_counts=event_counts)
    return table.pixels, log_divisor(table, c_on, c_off), None


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
        if _jit is not None:
            return _jit.log_divisor_levels(table.lvl_start, table.lvl_min, table.lvl_frac, c_on, LEVEL_CAP)
        return _log_divisor_levels_numpy(table, c_on)
    if table.seg_frac.size == 0:
        raise ValueError("this level table was built without segments; build it with segments=True for c_on != c_off")
    if _jit is not None:
        return _jit.log_divisor_segments(table.seg_start, table.seg_on, table.seg_off, table.seg_frac, c_on, c_off)
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


def blurry_to_float(image: np.ndarray, *, saturation: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """APS image (uint8/uint16/float) -> (B on the 8-bit scale as float32, informative mask).

    A pixel is uninformative when it is at 0 or at/above `saturation` (default: full scale of the dtype):
    a clipped value does not equal the mean of the latent intensity, so dividing it would be wrong.
    """
    img = np.asarray(image)
    if img.dtype == np.uint8:
        # the general path below gives exactly this: B = img (scale 1), always finite and >= 0
        sat = 255.0 if saturation is None else float(saturation)
        return img.astype(np.float32), (img > 0) & (img < sat)
    if img.dtype == np.uint16:
        full = 65535.0
    else:
        full = 255.0
    sat = full if saturation is None else float(saturation)
    b = img.astype(np.float32) * np.float32(255.0 / full)
    with np.errstate(invalid="ignore"):
        informative = (img > 0) & (img < sat) & np.isfinite(b)
    b = np.nan_to_num(b, nan=0.0, posinf=255.0, neginf=0.0)
    np.clip(b, 0.0, None, out=b)
    return b, informative


def deblur_log(blurry: np.ndarray, table: LevelTable | None, c_on: float, c_off: float | None = None, *,
               informative: np.ndarray | None = None,
               divisor: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """log L(f) on the 8-bit scale, (H, W) float32: log B - log D at active informative pixels, log B elsewhere.

    `blurry` is B as float (8-bit scale, see blurry_to_float); `informative` defaults to 0 < B < 255.
    log D comes from `table` at (c_on, c_off), or precomputed as `divisor` = (pixels, log D, ...).
    """
    b = np.asarray(blurry, dtype=np.float32)
    if table is not None and b.shape != (table.height, table.width):
        raise ValueError(f"blurry image shape {b.shape} does not match the table ({table.height}, {table.width})")
    out = np.log(np.maximum(b, DARK_FLOOR)).reshape(-1)
    if divisor is None and table is not None and table.n_active:
        divisor = (table.pixels, log_divisor(table, c_on, c_off))
    if divisor is not None and divisor[0].size:
        pix, ld = divisor[0], divisor[1]
        if informative is None:
            bp = b.reshape(-1)[pix]
            use = (bp > 0) & (bp < 255.0)
        else:
            use = informative.reshape(-1)[pix]
        out[pix[use]] -= ld[use].astype(np.float32)
    np.clip(out, LOG_MIN, LOG_MAX, out=out)
    return out.reshape(b.shape)


def deblur(blurry: np.ndarray, table: LevelTable, c_on: float, c_off: float | None = None, *,
           informative: np.ndarray | None = None, max_value: float = 4 * 255.0) -> np.ndarray:
    """Sharp L(f) = B / D(c), float32 (H, W) on the 8-bit scale, finite, clipped to [0, max_value]."""
    out = np.exp(deblur_log(blurry, table, c_on, c_off, informative=informative))
    np.clip(out, 0.0, max_value, out=out)
    return out


def event_delta(events: np.ndarray, width: int, height: int, c_on: float, c_off: float | None = None, *,
                t0: int | None = None, t1: int | None = None, mask: np.ndarray | None = None) -> np.ndarray:
    """c_on*n_on - c_off*n_off per pixel for events with t0 <= t <= t1, (H, W) float32 (dense)."""
    c_off = c_on if c_off is None else c_off
    idx, _, p = _select(events, width, height, t0, t1, mask)
    w = np.where(p, np.float64(c_on), -np.float64(c_off))
    return np.bincount(idx, weights=w, minlength=width * height).astype(np.float32).reshape(height, width)


def signed_counts(events: np.ndarray, width: int, height: int, *, t0: int | None = None, t1: int | None = None,
                  mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(n_on, n_off) per pixel as flat int64 arrays for events with t0 <= t <= t1 (time-ordered input)."""
    npix = width * height
    n_on = np.zeros(npix, np.int64)
    n_off = np.zeros(npix, np.int64)
    add_counts(events, width, height, n_on, n_off, t0=t0, t1=t1, mask=mask)
    return n_on, n_off


def add_counts(events: np.ndarray, width: int, height: int, n_on: np.ndarray, n_off: np.ndarray, *,
               t0: int | None = None, t1: int | None = None, mask: np.ndarray | None = None, sign: int = 1) -> None:
    """In place: n_on/n_off (flat int64) += sign * ON/OFF counts of the events with t0 <= t <= t1."""
    if _jit is not None:
        ev = _window(events, t0, t1)
        m, use_m = _mask_arg(mask)
        _jit.count_events(ev["x"], ev["y"], ev["p"], width, height, m, use_m, n_on, n_off, int(sign))
        return
    idx, _, p = _select(events, width, height, t0, t1, mask)
    n_on += sign * np.bincount(idx[p], minlength=n_on.size)
    n_off += sign * np.bincount(idx[~p], minlength=n_off.size)


def propagate_log(log_image: np.ndarray, events: np.ndarray, c_on: float, c_off: float | None = None, *,
                  sign: int = 1, mask: np.ndarray | None = None, display: np.ndarray | None = None,
                  gain: float = 1.0, counts: tuple[np.ndarray, np.ndarray] | None = None) -> int:
    """In place: log L += sign * (c_on * n_on - c_off * n_off) over `events`, touching only their pixels.

    sign=+1 moves forward in time (L(t) = L(f) exp(c E(f->t))), sign=-1 backward. If `display` (uint8, same
    shape) is given, it is refreshed at the touched pixels with clip(gain * exp(log L), 0, 255). If `counts`
    (flat int64 n_on, n_off arrays) is given, the applied events are added to it.
    Returns the number of events applied. log L stays within [LOG_MIN, LOG_MAX].
    """
    c_off = c_on if c_off is None else c_off
    h, w = log_image.shape
    flat = log_image.reshape(-1)
    d_on = float(sign) * float(c_on)
    d_off = -float(sign) * float(c_off)
    if _jit is not None and flat.dtype == np.float32 and log_image.flags.c_contiguous and (
            display is None or display.flags.c_contiguous):
        ev = _window(events, None, None)
        m, use_m = _mask_arg(mask)
        disp = display.reshape(-1) if display is not None else _NO_MASK
        acc_on, acc_off = counts if counts is not None else (_NO_COUNTS, _NO_COUNTS)
        return int(_jit.propagate(ev["x"], ev["y"], ev["p"], w, h, m, use_m, flat, d_on, d_off, LOG_MIN, LOG_MAX,
                                  disp, display is not None, float(gain), acc_on, acc_off, counts is not None))
    idx, _, p = _select(events, w, h, None, None, mask)
    if idx.size == 0:
        return 0
    if idx.size * 8 < flat.size:
        # small batch: unbuffered add at the touched pixels only
        np.add.at(flat, idx, np.where(p, np.float32(d_on), np.float32(d_off)))
        if counts is not None:
            np.add.at(counts[0], idx[p], 1)
            np.add.at(counts[1], idx[~p], 1)
    else:
        flat += np.bincount(idx, weights=np.where(p, d_on, d_off), minlength=flat.size).astype(flat.dtype)
        if counts is not None:
            on_counts, off_counts = counts
            on_counts += np.bincount(idx[p], minlength=flat.size)
            off_counts += np.bincount(idx[~p], minlength=flat.size)
    flat[idx] = np.clip(flat[idx], LOG_MIN, LOG_MAX)
    if display is not None:
        display.reshape(-1)[idx] = to_uint8(flat[idx], gain)
    return int(idx.size)


def to_uint8(log_values: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """clip(gain * exp(log L), 0, 255) rounded to uint8."""
    v = np.exp(np.minimum(log_values, 6.0)) * gain  # exp(6) > 255 already; avoids overflow in float32
    return np.clip(v + 0.5, 0.0, 255.0).astype(np.uint8)


def hot_pixel_mask(counts: np.ndarray, duration_us: float, *, min_rate_hz: float = 300.0,
                   rel_factor: float = 10.0) -> np.ndarray:
    """Hot pixels from per-pixel event counts over `duration_us`: a pixel is hot when its rate exceeds
    `min_rate_hz` AND its count exceeds `rel_factor` times the mean count over active pixels.

    Moving edges spread their events over many pixels, so they raise the mean; a stuck pixel fires alone.
    Accumulate `counts` over several frames so edges average out.
    """
    counts = np.asarray(counts)
    active = counts > 0
    if not active.any() or duration_us <= 0:
        return np.zeros(counts.shape, dtype=bool)
    mean_active = float(counts[active].mean())
    rate_hz = counts * (1e6 / float(duration_us))
    return (rate_hz > min_rate_hz) & (counts > rel_factor * mean_active)


def new_activity_map(width: int, height: int) -> np.ndarray:
    """State for background_activity_keep: latest event time per pixel, padded by one pixel, 'long ago'."""
    return np.full((height + 2, width + 2), -(2**62), dtype=np.int64)


def background_activity_keep(events: np.ndarray, width: int, height: int, last_t: np.ndarray,
                             dt_us: int) -> np.ndarray:
    """Per event: True when one of its 8 neighbours fired within dt_us before it (time-ordered input).
    `last_t` (from new_activity_map) is updated in place, so successive batches form one stream."""
    keep = np.empty(len(events), dtype=bool)
    if _jit is not None:
        _jit.background_activity(events["t"], events["x"], events["y"], width, height, last_t, int(dt_us), keep)
        return keep
    for i, (t, x, y) in enumerate(zip(events["t"].tolist(), events["x"].tolist(), events["y"].tolist())):
        if x >= width or y >= height:
            keep[i] = False
            continue
        block = last_t[y:y + 3, x:x + 3]
        keep[i] = bool(((t - block) <= dt_us).sum() - ((t - block[1, 1]) <= dt_us) > 0)
        last_t[y + 1, x + 1] = t
    return keep


def supported_events_keep(events: np.ndarray, width: int, height: int, dt_us: int) -> np.ndarray:
    """Per event of one batch: True when one of its 8 neighbours fired within dt_us before OR after it.
    The two-sided, stateless form of the background-activity filter, for a whole exposure at once."""
    fwd = background_activity_keep(events, width, height, new_activity_map(width, height), dt_us)
    rev = events[::-1].copy()
    rev["t"] = -rev["t"]
    bwd = background_activity_keep(rev, width, height, new_activity_map(width, height), dt_us)[::-1]
    return fwd | bwd


def isolated_event_mask(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels with exactly one event in `events` and no event in their 8 neighbours.

    A background-activity filter at window granularity: such lone events are most likely noise.
    """
    import cv2  # local: cv2 is only needed by the optional filters

    idx, _, _ = _select(events, width, height, None, None, None)
    counts = np.bincount(idx, minlength=width * height).reshape(height, width).astype(np.float32)
    neigh = cv2.boxFilter(counts, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT) - counts
    return (counts == 1) & (neigh == 0)


__all__ = [
    "LevelTable", "build_level_table", "log_divisor", "log_divisor_events", "deblur", "deblur_log",
    "blurry_to_float", "event_delta", "signed_counts", "add_counts", "propagate_log", "to_uint8", "time_index",
    "hot_pixel_mask", "isolated_event_mask", "new_activity_map", "background_activity_keep",
    "supported_events_keep", "flat_index", "events_at_pixels", "have_numba", "empty_table", "LEVEL_CAP",
    "LOG_MIN", "LOG_MAX",
]
