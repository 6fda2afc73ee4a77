"""The residual estimate of a pair's fused frames as a schedule of changes: per pixel, the frames at which its
estimate (edi_live.edi.residual) changes and the new value, plus what the two references already hold of it.

The estimate r(t) of a pixel is a step function of t: it changes at the pixel's events, where x crosses a table
bin, where the next event comes within the seen range and where the last one leaves it. On the benchmark's
scenes that is ~6000 pixel changes per frame against ~35000 pixels with an estimate, so a pair's frames are
rendered from the changes (edi_live.edi.fused) instead of a pass over the pixels per frame. The values are the
ones ResidualTracker gives at the same times with the same seen ranges (the same float operations per pixel).

`ResidualCarry` keeps what one pair leaves for the next: each pixel's last event a little before the newer
frame (SNAP_BACK of the interval, more than the span the next pair's held residual of that frame averages over)
and the estimate at the last frame, so the next pair reads only the events after that time instead of four
intervals of context, and its first frame changes only the pixels whose estimate changed. Both references' held
residuals are still computed from the events of the current window, so the frames are the same with the carry as
without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edi_live.edi import _backend, _kernels_schedule
from edi_live.edi.residual import _NEVER, A_UNKNOWN, EXPOSURE_SAMPLES, TABLE_A, TABLE_B, exposure_samples
from edi_live.edi.selection import time_index

COLD_CONTEXT = 4  # intervals of events before f0 a pair needs without a warm carry (> the held residual's 3.3)
SNAP_BACK = 0.4  # the carry's snapshot: this share of the interval before the newer frame (> RESIDUAL_SPAN)
FORGET_SPANS = 10  # a pixel's last event is seen for this many spans (edi_live.edi.fused.residual_seen)


@dataclass
class ResidualCarry:
    """What the last pair's pass left: every pixel's last event at or before snap_us (time, polarity 1 ON / 2 OFF
    / 0 none; masked pixels' events left out), for the pair that starts at f_us with that mask, and the estimate
    at the last frame rendered. Owned by whoever renders consecutive pairs (the reconstructor); `clear` after lost
    data."""

    f_us: int | None = None
    snap_us: int = 0
    last_t: np.ndarray | None = None
    last_p: np.ndarray | None = None
    residual: np.ndarray | None = None
    mask: np.ndarray | None = None
    _scratch: dict | None = None

    def clear(self) -> None:
        self.f_us = None

    def scratch(self, name: str, size: int, dtype: type) -> np.ndarray:
        """A work array of at least `size` kept from pair to pair (its pages are not faulted in again each
        time), contents undefined."""
        if self._scratch is None:
            self._scratch = {}
        a = self._scratch.get(name)
        if a is None or a.size < size:
            a = self._scratch[name] = np.empty(max(size, 0 if a is None else 2 * a.size), dtype)
        return a[:size]

    def warm(self, f0_us: int, span: int, mask: np.ndarray | None) -> bool:
        """True when the pair starting at f0 (its held residuals averaged over `span` either side) can start from
        this carry: the same frame and mask, and the snapshot before the earliest time the held residual of f0
        looks at."""
        if self.f_us is None or self.f_us != int(f0_us) or int(f0_us) - span <= self.snap_us:
            return False
        if (mask is None) != (self.mask is None):
            return False
        return mask is None or np.array_equal(mask, self.mask)


@dataclass(frozen=True)
class ResidualChanges:
    """held0/held1: the residual the references hold (H, W) float32; `start`: the estimate before frame 0 (flat
    float32); frame j's changes: pixels q[offsets[j]:offsets[j + 1]] take values v[...] (flat indices). With a
    carry, q and v are views of its scratch memory: valid until the next residual_changes call with that carry
    (the caller renders the pair's frames first; copying them would cost ~0.2 ms a pair)."""

    held0: np.ndarray
    held1: np.ndarray
    start: np.ndarray
    offsets: np.ndarray
    q: np.ndarray
    v: np.ndarray


def residual_changes(events: np.ndarray, width: int, height: int, c: tuple[float, float], mask: np.ndarray | None,
                     f0_us: int, f1_us: int, span: int, frames: np.ndarray,
                     carry: ResidualCarry | None = None) -> ResidualChanges:
    """The schedule of the estimate at `frames` (ascending, inside (f0, f1)) with the seen ranges of
    edi_live.edi.fused.residual_seen, and the held residuals of both references. `events`: from COLD_CONTEXT
    intervals before f0 to the newer frame's exposure end, or from just after carry.snap_us when `carry` is warm for this
    pair (it is updated for the next one either way). Needs the numba kernels."""
    n_px = width * height
    warm = carry is not None and carry.warm(f0_us, span, mask)
    t = events["t"]
    if warm:
        last_t, last_p = carry.last_t, carry.last_p
        start = time_index(t, carry.snap_us, "right")
    else:
        last_t, last_p = np.zeros(n_px, np.int64), np.zeros(n_px, np.int8)
        start = 0
    refs = [f0_us, f1_us]
    samples, s_row, s_from, s_to = [], [], [], []
    for row, f in enumerate(refs):
        ts, (lo, hi) = exposure_samples(int(f) - span, int(f) + span)
        samples += ts
        s_row += [row] * len(ts)
        s_from += [lo] * len(ts)
        s_to += [hi] * len(ts)
    acc = np.zeros((2, n_px), np.float32)
    m, use_m = _backend.mask_arg(mask)
    frames = np.ascontiguousarray(frames, np.int64)
    start_res = carry.residual if warm else np.zeros(n_px, np.float32)
    snap_t, snap_p = np.empty(n_px, np.int64), np.empty(n_px, np.int8)
    snap_us = int(f1_us) - int(SNAP_BACK * (f1_us - f0_us))
    capacity = 3 * (t.size - start) + 2 * n_px
    work = carry if carry is not None else ResidualCarry()
    while True:
        ent_f, ent_q = work.scratch("f", capacity, np.int32), work.scratch("q", capacity, np.int32)
        ent_v = work.scratch("v", capacity, np.float32)
        lt, lp = work.scratch("last_t", n_px, np.int64), work.scratch("last_p", n_px, np.int8)
        lt[:], lp[:] = last_t, last_p
        acc[:] = 0.0
        cur = start_res.copy()
        n_ent = _kernels_schedule.schedule(
            events["x"], events["y"], events["p"], t, start, width, height, m, use_m, lt, lp, np.int64(snap_us), snap_t,
            snap_p, frames, np.int64(span), np.int64(FORGET_SPANS * span), np.int64(_NEVER), np.float32(c[0]),
            np.float32(c[1]), TABLE_A, TABLE_B, np.float32(A_UNKNOWN), np.array(samples, np.int64),
            np.array(s_row, np.int64), np.array(s_from, np.int64), np.array(s_to, np.int64), acc, cur, ent_f, ent_q,
            ent_v)
        if n_ent <= capacity:
            break
        capacity = 2 * n_ent  # the entries did not fit: again, from the same start
    acc /= np.float32(EXPOSURE_SAMPLES)
    held0, held1 = acc[0].reshape(height, width), acc[1].reshape(height, width)
    offsets = np.empty(frames.size + 1, np.int64)
    q_sorted, v_sorted = work.scratch("q_sorted", n_ent, np.int32), work.scratch("v_sorted", n_ent, np.float32)
    _kernels_schedule.by_frame(ent_f, ent_q, ent_v, n_ent, frames.size, offsets, q_sorted, v_sorted)
    if carry is not None:
        carry.f_us, carry.snap_us, carry.last_t, carry.last_p = int(f1_us), snap_us, snap_t, snap_p
        carry.residual = cur
        carry.mask = None if mask is None else np.array(mask, bool)
    return ResidualChanges(held0, held1, start_res, offsets, q_sorted, v_sorted)
