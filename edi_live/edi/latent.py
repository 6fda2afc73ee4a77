"""The latent image: moving log L along the events, and rendering log intensities as uint8 images.

L(t) = L(f) * exp(c_on * n_on(f->t) - c_off * n_off(f->t)) per pixel, applied in place on a float32 log image.
Rendering is clip(gain * exp(log L), 0, 255) rounded; `render_buckets` (float32 log L) and `display_buckets` (the
propagation's float64 sums) give the same rounding as lookups that the kernels use instead of exp.
"""

from __future__ import annotations

import functools

import numpy as np

from edi_live.edi import _backend, _kernels_stream
from edi_live.edi._backend import DARK_FLOOR, LOG_MAX, LOG_MIN
from edi_live.edi.selection import select, window


def event_delta(events: np.ndarray, width: int, height: int, c_on: float, c_off: float | None = None, *,
                t0: int | None = None, t1: int | None = None, mask: np.ndarray | None = None) -> np.ndarray:
    """c_on*n_on - c_off*n_off per pixel for events with t0 <= t <= t1, (H, W) float32 (dense)."""
    c_off = c_on if c_off is None else c_off
    idx, _, p = select(events, width, height, t0, t1, mask)
    w = np.where(p, np.float64(c_on), -np.float64(c_off))
    return np.bincount(idx, weights=w, minlength=width * height).astype(np.float32).reshape(height, width)


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
    if _backend.have_numba() and flat.dtype == np.float32 and log_image.flags.c_contiguous and (
            display is None or display.flags.c_contiguous):
        tables = (display_buckets(float(gain)) or NO_TABLE) if display is not None else NO_TABLE
        ev = window(events, None, None)
        m, use_m = _backend.mask_arg(mask)
        disp = display.reshape(-1) if display is not None else _backend.NO_MASK
        acc_on, acc_off, use_counts = _backend.counts_arg(counts)
        return int(_kernels_stream.propagate(ev["x"], ev["y"], ev["p"], w, h, m, use_m, flat, d_on, d_off, LOG_MIN,
                                             LOG_MAX, disp, display is not None, float(gain), *tables, acc_on, acc_off,
                                             use_counts))
    idx, _, p = select(events, w, h, None, None, mask)
    return _propagate_numpy(flat, idx, p, d_on, d_off, display, gain, counts)


def _propagate_numpy(flat: np.ndarray, idx: np.ndarray, p: np.ndarray, d_on: float, d_off: float,
                     display: np.ndarray | None, gain: float, counts: tuple[np.ndarray, np.ndarray] | None) -> int:
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


class Propagator:
    """propagate_log(sign=+1, gain=1) with its arguments bound once: for a stream of event slices applied to the
    same float32 log image and uint8 display (the worker's hot path makes a latent frame every few hundred events,
    and re-deriving the kernel arguments per slice cost ~5 µs of a ~25 µs frame). Slices are given as the `x`,
    `y`, `p` field views of time-ordered events."""

    def __init__(self, log_image: np.ndarray, display: np.ndarray, c_on: float, c_off: float,
                 mask: np.ndarray | None, counts: tuple[np.ndarray, np.ndarray] | None) -> None:
        if log_image.dtype != np.float32 or not (log_image.flags.c_contiguous and display.flags.c_contiguous):
            raise ValueError("Propagator needs a C-contiguous float32 log image and uint8 display")
        self._h, self._w = log_image.shape
        self._flat = log_image.reshape(-1)
        self._disp = display.reshape(-1)
        self._display = display
        self._mask = mask
        self._m, self._use_m = _backend.mask_arg(mask)
        self._counts = counts
        self._acc_on, self._acc_off, self._use_counts = _backend.counts_arg(counts)
        self._d_on, self._d_off = float(c_on), -float(c_off)
        self._tables = (display_buckets(1.0) or NO_TABLE) if _backend.have_numba() else None  # the path, fixed here

    def apply(self, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> None:
        if self._tables is not None:
            _kernels_stream.propagate(x, y, p, self._w, self._h, self._m, self._use_m, self._flat, self._d_on,
                                      self._d_off, LOG_MIN, LOG_MAX, self._disp, True, 1.0, *self._tables,
                                      self._acc_on, self._acc_off, self._use_counts)
            return
        idx = y.astype(np.int64) * self._w + x
        keep = (x < self._w) & (y < self._h)
        if self._mask is not None:
            keep &= ~self._mask.reshape(-1)[np.minimum(idx, self._w * self._h - 1)]
        _propagate_numpy(self._flat, idx[keep], np.asarray(p[keep], bool), self._d_on, self._d_off, self._display,
                         1.0, self._counts)


def to_uint8(log_values: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """clip(gain * exp(log L), 0, 255) rounded to uint8."""
    v = np.exp(np.minimum(log_values, 6.0)) * gain  # exp(6) > 255 already; avoids overflow in float32
    return np.clip(v + 0.5, 0.0, 255.0).astype(np.uint8)


@functools.lru_cache(maxsize=64)
def u8_tables(black_level: float = 0.0, gamma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """For every uint8 B: log L(f) where no event moved it (clipped log(max(B linearised, floor)), see
    blurry_to_float), and its uint8 image."""
    b = np.maximum(np.arange(256, dtype=np.float32) - np.float32(black_level), np.float32(0.0))
    if gamma != 1.0:
        b = (np.float32(255.0) * (b / np.float32(255.0)) ** np.float32(gamma)).astype(np.float32)
    log_b = np.clip(np.log(np.maximum(b, DARK_FLOOR)), LOG_MIN, LOG_MAX).astype(np.float32)
    return log_b, to_uint8(log_b)


@functools.lru_cache(maxsize=1)
def render_buckets(n_buckets: int = 8192) -> tuple[float, float, np.ndarray, np.ndarray]:
    """to_uint8 as a step function of float32 log L, for rendering without exp: the smallest float32 at
    which each value 1..255 starts (found by bisection on to_uint8 itself, so the same rounding), and
    buckets over [first, last threshold) narrower than any gap between thresholds (at most one per bucket).
    Returns (v0, buckets per unit of log L, uint8 value at each bucket start, the bucket's threshold or inf)."""
    lo = np.full(255, -8.0, np.float32)  # to_uint8(-8) = 0 < k
    hi = np.full(255, 6.0, np.float32)  # to_uint8(6) = 255 >= k
    k = np.arange(1, 256)
    for _ in range(60):  # bisection down to adjacent float32 values
        mid = _f32_midpoint(lo, hi)
        up = to_uint8(mid) >= k
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    thr = hi.astype(np.float64)  # thr[k-1]: the first float32 rendered as >= k
    v0 = float(thr[0])
    scale = n_buckets / (float(thr[-1]) - v0)
    _, bucket_u8, bucket_thr = _buckets(thr, v0, scale, n_buckets)
    return v0, scale, bucket_u8, bucket_thr.astype(np.float32)


def _buckets(thr: np.ndarray, v0: float, scale: float, n_buckets: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(each bucket's start, the uint8 value there, the threshold inside the bucket or inf) for the ascending
    thresholds `thr` of the values 1..255 and buckets of width 1 / scale from v0 (at most one threshold each)."""
    starts = v0 + np.arange(n_buckets) / scale
    bucket_u8 = np.searchsorted(thr, starts, side="right").astype(np.uint8)
    bucket_thr = np.full(n_buckets, np.inf)
    owner = np.minimum(((thr - v0) * scale).astype(np.int64), n_buckets - 1)
    inside = thr > starts[owner]
    bucket_thr[owner[inside]] = thr[inside]
    return starts, bucket_u8, bucket_thr


NO_TABLE = (0.0, 0.0, np.zeros(0, np.uint8), np.zeros(0, np.float64))  # propagate renders with exp


@functools.lru_cache(maxsize=8)
def display_buckets(gain: float = 1.0) -> tuple[float, float, np.ndarray, np.ndarray] | None:
    """The propagation kernel's display rendering as a lookup: clip(gain * exp(v), 0, 255) rounded, for the
    float64 sum v (flat float32 + float64 step, clipped to [LOG_MIN, LOG_MAX]) before it is rounded to float32,
    exactly as _kernels_stream.display_u8 computes it with exp (an exp an event cost ~2 ns of ~9). The threshold
    of each value 1..255 is the smallest float64 at which display_u8 reaches it (bisection down to adjacent
    doubles), and the table is checked against display_u8 around every threshold and bucket start; both being
    step functions that only rise, agreeing at every step means agreeing everywhere. Returns (v0, buckets per
    unit of log L, uint8 value at each bucket start, the bucket's threshold or inf), or None for a gain whose
    values 1..255 do not all start within (LOG_MIN, 6], or if a check ever failed: the kernel then renders with
    exp (NO_TABLE)."""
    k = np.arange(1, 256)
    lo = np.full(255, LOG_MIN)
    hi = np.full(255, 6.0)
    if _display(lo, gain)[0] >= 1 or _display(hi, gain)[-1] < 255:
        return None
    for _ in range(2100):  # halving takes ~1100 steps at worst (a threshold near 0, where doubles are densest);
        # it stops once lo, hi are adjacent
        mid = lo + (hi - lo) / 2
        moved = (mid > lo) & (mid < hi)
        if not moved.any():
            break
        up = _display(mid, gain) >= k
        hi = np.where(moved & up, mid, hi)
        lo = np.where(moved & ~up, mid, lo)
    thr = hi  # thr[k-1]: the first float64 rendered as >= k
    gap = float(np.diff(thr).min())
    v0 = float(thr[0])
    n_buckets = 1 << int(np.ceil(np.log2(1.01 * (float(thr[-1]) - v0) / gap)))  # each at most one threshold
    scale = n_buckets / ((float(thr[-1]) - v0) * (1.0 + 2.0**-20))  # the last threshold inside the last bucket
    starts, bucket_u8, bucket_thr = _buckets(thr, v0, scale, n_buckets)
    tables = (v0, scale, bucket_u8, bucket_thr)
    near = np.concatenate([thr, starts, [LOG_MIN, LOG_MAX, 6.0]])
    probe = np.concatenate([_ulps_around(near, 64), [-np.inf, np.inf]]).clip(LOG_MIN, LOG_MAX)
    looked_up = np.empty(probe.size, np.uint8)
    _kernels_stream.display_u8_table(probe, *tables, looked_up)
    if not np.array_equal(looked_up, _display(probe, gain)):
        return None  # exp not monotone here? never seen; the kernel's exp is then used as before
    return tables


def _display(v: np.ndarray, gain: float) -> np.ndarray:
    out = np.empty(v.size, np.uint8)
    _kernels_stream.display_u8(np.ascontiguousarray(v, np.float64), float(gain), out)
    return out


def _ulps_around(v: np.ndarray, n: int) -> np.ndarray:
    """Every float64 within n steps of each v."""
    bits = np.ascontiguousarray(v, np.float64).view(np.int64)[:, None] + np.arange(-n, n + 1)[None, :]
    return bits.view(np.float64).reshape(-1)


def _f32_midpoint(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A float32 strictly between a and b (a < b) when one exists, else a: bisection then stays put."""
    m = ((a.astype(np.float64) + b.astype(np.float64)) / 2).astype(np.float32)
    step = np.nextafter(a, b)
    return np.where((m > a) & (m < b), m, np.where(step < b, step, a)).astype(np.float32)


