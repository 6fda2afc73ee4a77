"""The sub-threshold residual between a pixel's events: where log L most likely is at t, relative to the level
of the pixel's last threshold crossing, given that event's polarity and the polarity and time of the next one.

The step model of EDI puts a pixel exactly on its last crossing level until its next event. The truth lies
anywhere between the levels below and above (a band of c_off + c_on), and on the benchmark's ideal scenes this
unobserved residual is the largest error left in fused latent frames (docs/modes.md, "Residual"): it is common
to the forward and the backward side, so blending them cannot remove it. Once the next event is known (fused
mode waits for the next APS frame anyway), the residual's conditional mean is, per pixel,

    r(t) = A(x) s_a c_a + B(x) s_b c_b,     x = (t - t_a) / (t_b - t_a)

with s_a, c_a the sign and threshold of the last event (at t_a) and s_b, c_b those of the next one (at t_b):
the level keeps drifting a little past the last crossing in its direction (A about 0.25) and approaches the
next crossing late in the gap (B rising from 0 to about 0.7). Without a next event yet: r = A_UNKNOWN s_a c_a;
without a last event in the window: 0 (the step). A and B in NBINS bins of x are the least-squares fit of the
simulator's true residual (ideal scenes of tools/bench_accuracy, first 0.2 s; tools/fit_residual.py refits
them). `ResidualTracker` streams a window's events and gives the estimate at ascending times in O(active pixels)
per time (the reference for edi_live.edi.residual_schedule, which the fused frames use); `exposure_residual` averages it near a reference frame, which is what that frame's deblurred value
already holds of the residual (it averages the truth over its exposure).
"""

from __future__ import annotations

import numpy as np

from edi_live.edi import _backend, _kernels_residual
from edi_live.edi._backend import LOG_MAX, LOG_MIN
from edi_live.edi.latent import render_buckets, to_uint8
from edi_live.edi.selection import time_index, window

TABLE_A = np.array([0.157, 0.245, 0.259, 0.257, 0.243, 0.228, 0.209, 0.194, 0.165, 0.088], np.float32)
TABLE_B = np.array([-0.018, 0.011, 0.038, 0.067, 0.101, 0.143, 0.197, 0.277, 0.406, 0.696], np.float32)
_NEVER = np.iinfo(np.int64).max // 2
A_UNKNOWN = 0.22  # the mean of A over x: the residual after the last event when the next is not known yet


class ResidualTracker:
    """The residual estimate of each pixel at ascending times, from a window of time-ordered events (the links to
    each event's successor are made once, O(events))."""

    def __init__(self, events: np.ndarray, width: int, height: int, c_on: float, c_off: float,
                 mask: np.ndarray | None = None, start_us: int | None = None) -> None:
        """`start_us`: the earliest time `at` will be asked for (the events before it are context only: each
        pixel's last event is found in the same pass that links them)."""
        self.events = window(events, None, None)
        self._w, self._h = width, height
        self.c_on, self.c_off = np.float32(c_on), np.float32(c_off)
        self._m, self._use_m = _backend.mask_arg(mask)
        n = self.events.size
        self.next = np.empty(n, np.int64)
        first = np.full(width * height, -1, np.int64)
        ev = self.events
        self.times = np.ascontiguousarray(ev["t"], np.int64)
        self.polarity = np.ascontiguousarray(ev["p"])
        self._start = 0 if start_us is None else time_index(self.times, int(start_us), "right")
        self._before = np.full(width * height, -1, np.int64)
        if _backend.have_numba():
            _kernels_residual.link_next(ev["x"], ev["y"], width, height, self._m, self._use_m, self._start, self.next,
                                        first, self._before)
        else:
            idx = self._valid_index(0, n)
            _link_next_numpy(idx, self.next, first)
            early = np.flatnonzero(idx[:self._start] >= 0)
            np.maximum.at(self._before, idx[early], early)
        self.active = np.flatnonzero(first >= 0)
        self.residual = np.zeros(width * height, np.float32)
        self.restart()

    def restart(self) -> None:
        """Back to `start_us` (the window's start without one)."""
        n = self._w * self._h
        self.last_t = np.zeros(n, np.int64)  # each pixel's last event so far: time, signed threshold (0: none)
        self.last_c = np.zeros(n, np.float32)
        self.next_t = np.full(n, _NEVER, np.int64)  # and the event after it (_NEVER, 0: none in the window)
        self.next_c = np.zeros(n, np.float32)
        if _backend.have_numba():
            _kernels_residual.start_from(self._before, self.times, self.polarity, self.next, self.c_on, self.c_off,
                                         np.int64(_NEVER), self.last_t, self.last_c, self.next_t, self.next_c)
        else:
            self._set_last(np.flatnonzero(self._before >= 0), self._before[self._before >= 0])
        self._pos = self._start

    def at(self, t_us: int, seen: tuple[int, int] | None = None) -> np.ndarray:
        """The flat float32 residual estimate at t (>= the previous call's t) at the active pixels; zero at the
        pixels without events in the window. `seen` = (from, to): as if only the events in that time range were
        known (an estimate that does not depend on how wide the window is). The returned array is reused by the
        next call."""
        self._update(t_us, seen)
        return self.residual

    def at_painted(self, t_us: int, seen: tuple[int, int] | None, log_image: np.ndarray,
                   display: np.ndarray) -> None:
        """`at`, then `paint` (in one pass over the active pixels with the kernels)."""
        if not _backend.have_numba():
            self.at(t_us, seen)
            self.paint(log_image, display)
            return
        lo, hi = self._update(t_us, seen, estimate=False)
        _kernels_residual.residual_paint(np.int64(t_us), self.active, self.last_t, self.last_c, self.next_t,
                                         self.next_c, TABLE_A, TABLE_B, np.float32(A_UNKNOWN), np.int64(lo),
                                         np.int64(hi), self.residual, log_image.reshape(-1), np.float32(LOG_MIN),
                                         np.float32(LOG_MAX), display.reshape(-1), *render_buckets())

    def _update(self, t_us: int, seen: tuple[int, int] | None, estimate: bool = True) -> tuple[int, int]:
        """Advance to t and (`estimate`) the residual at the active pixels; returns the seen range."""
        lo, hi = seen if seen is not None else (-_NEVER, _NEVER - 1)
        start = self._pos
        end = max(time_index(self.times, int(t_us), "right"), start)
        ev = self.events
        if _backend.have_numba():
            _kernels_residual.advance(ev["x"], ev["y"], self.polarity, self.times, self.next, self._w, self._h,
                                      self._m, self._use_m, start, end, self.c_on, self.c_off, np.int64(_NEVER),
                                      self.last_t, self.last_c, self.next_t, self.next_c)
            if estimate:
                _kernels_residual.residual_at(np.int64(t_us), self.active, self.last_t, self.last_c, self.next_t,
                                              self.next_c, TABLE_A, TABLE_B, np.float32(A_UNKNOWN), np.int64(lo),
                                              np.int64(hi), self.residual)
        else:
            self._advance_numpy(start, end)
            q = self.active
            self.residual[q] = _residual_numpy(int(t_us), self.last_t[q], self.last_c[q], self.next_t[q],
                                               self.next_c[q], lo, hi)
        self._pos = end
        return lo, hi

    def paint(self, log_image: np.ndarray, display: np.ndarray) -> None:
        """display (uint8, in place) = the image of log_image + residual at the active pixels."""
        flat, disp = log_image.reshape(-1), display.reshape(-1)
        if _backend.have_numba():
            _kernels_residual.render_with(flat, self.residual, self.active, np.float32(LOG_MIN), np.float32(LOG_MAX),
                                          disp, *render_buckets())
            return
        q = self.active
        disp[q] = to_uint8(np.clip(flat[q] + self.residual[q], LOG_MIN, LOG_MAX).astype(np.float32))

    def _advance_numpy(self, start: int, end: int) -> None:
        idx = self._valid_index(start, end)
        keep = np.flatnonzero(idx >= 0)
        if keep.size == 0:
            return
        last = np.full(self._w * self._h, -1, np.int64)
        np.maximum.at(last, idx[keep], start + keep)  # the newest of this batch's events per pixel
        px = np.flatnonzero(last >= 0)
        self._set_last(px, last[px])

    def _set_last(self, px: np.ndarray, i: np.ndarray) -> None:
        on = self.polarity[i].astype(bool)
        self.last_t[px] = self.times[i]
        self.last_c[px] = np.where(on, self.c_on, -self.c_off)
        b = self.next[i]
        has = b >= 0
        bb = np.where(has, b, 0)
        self.next_t[px] = np.where(has, self.times[bb], _NEVER)
        self.next_c[px] = np.where(has, np.where(self.polarity[bb].astype(bool), self.c_on, -self.c_off), 0.0)

    def _valid_index(self, start: int, end: int) -> np.ndarray:
        """Flat pixel index of events start..end-1, -1 for events off the sensor or masked."""
        ev = self.events[start:end]
        x, y = ev["x"].astype(np.int64), ev["y"].astype(np.int64)
        ok = (x < self._w) & (y < self._h)
        idx = np.where(ok, y * self._w + x, -1)
        if self._use_m:
            ok &= self._m[np.where(ok, idx, 0)] == 0
            idx = np.where(ok, idx, -1)
        return idx


EXPOSURE_SAMPLES = 4  # times exposure_residual averages the estimate at


def exposure_samples(t0: int, t1: int, samples: int = EXPOSURE_SAMPLES) -> tuple[list[int], tuple[int, int]]:
    """(the `samples` times evenly inside [t0, t1] at which exposure_residual takes the estimate, the seen range
    [t0 - 5 (t1 - t0), t1] of the events it uses: the same value whichever window holds them)."""
    return [t0 + (t1 - t0) * (2 * j + 1) // (2 * samples) for j in range(samples)], (t0 - 5 * (t1 - t0), t1)


def exposure_residual(tracker: ResidualTracker, t0: int, t1: int, samples: int = EXPOSURE_SAMPLES) -> np.ndarray:
    """The mean residual estimate at exposure_samples(t0, t1) (the tracker must not be past t0), flat float32."""
    acc = np.zeros_like(tracker.residual)
    times, seen = exposure_samples(t0, t1, samples)
    for t in times:
        acc += tracker.at(t, seen)
    acc /= np.float32(samples)
    return acc


def _link_next_numpy(idx: np.ndarray, nxt: np.ndarray, first: np.ndarray) -> None:
    nxt[:] = -1
    valid = np.flatnonzero(idx >= 0)
    order = valid[np.argsort(idx[valid], kind="stable")]
    q = idx[order]
    same = q[1:] == q[:-1]
    nxt[order[:-1][same]] = order[1:][same]
    starts = np.ones(q.size, bool)
    starts[1:] = ~same
    first[q[starts]] = order[starts]


def _residual_numpy(t: int, last_t: np.ndarray, last_c: np.ndarray, next_t: np.ndarray, next_c: np.ndarray,
                    seen_from: int, seen_to: int) -> np.ndarray:
    out = np.zeros(last_t.size, np.float32)
    has_a = (last_c != 0) & (last_t >= seen_from)
    unknown = has_a & (next_t > seen_to)
    out[unknown] = np.float32(A_UNKNOWN) * last_c[unknown]
    both = has_a & ~unknown
    span = next_t - last_t
    x = np.where(span > 0, (t - last_t) * (TABLE_A.size / np.where(span > 0, span, 1)), TABLE_A.size)
    i = np.clip(x.astype(np.int64), 0, TABLE_A.size - 1)  # as the kernels: (t - t_a) * (bins / span), no x
    out[both] = (TABLE_A[i] * last_c + TABLE_B[i] * next_c)[both]
    return out
