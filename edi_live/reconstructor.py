"""EdiReconstructor: the only stateful piece of the EDI math. Runs on the worker thread (not thread-safe).

Owns: the reference L(f) of the latest APS frame (log domain), the current contrast thresholds (cached, re-estimated
when the estimator's cheap fit test fails or every `reestimate_every` frames), the hot-pixel mask, and the latent
state L(t) with an incrementally maintained uint8 display buffer. Emitting a latent frame costs O(new events) plus
one copy of the image.

Time contract (µs, sensor clock): `on_frame(frame, events)` gets every event from frame.exposure_start_us up to the
caller's "now" (some of them may already have been given to `on_events`); `on_events` gets later events in time
order. Events before the first APS frame only feed the hot-pixel statistics (there is no reference yet).
"""

from __future__ import annotations

import collections
import copy
import functools
import math
import time
from typing import Sequence

import numpy as np

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.datatypes import Frame, Reconstruction
from edi_live.errors import ConfigError, NodeError

C_RANGE = (0.01, 2.0)


@functools.lru_cache(maxsize=1)
def _u8_tables() -> tuple[np.ndarray, np.ndarray]:
    """For every uint8 B: log L(f) where no event moved it (clipped log(max(B, floor))), and its uint8 image."""
    b, _ = edi.blurry_to_float(np.arange(256, dtype=np.uint8))
    log_b = np.clip(np.log(np.maximum(b, edi.DARK_FLOOR)), edi.LOG_MIN, edi.LOG_MAX).astype(np.float32)
    return log_b, edi.to_uint8(log_b)


@functools.lru_cache(maxsize=1)
def _render_buckets(n_buckets: int = 8192) -> tuple[float, float, np.ndarray, np.ndarray]:
    """edi.to_uint8 as a step function of float32 log L, for rendering without exp: the smallest float32 at
    which each value 1..255 starts (found by bisection on edi.to_uint8 itself, so the same rounding), and
    buckets over [first, last threshold) narrower than any gap between thresholds (at most one per bucket).
    Returns (v0, buckets per unit of log L, uint8 value at each bucket start, the bucket's threshold or inf)."""
    lo = np.full(255, -8.0, np.float32)  # edi.to_uint8(-8) = 0 < k
    hi = np.full(255, 6.0, np.float32)  # edi.to_uint8(6) = 255 >= k
    k = np.arange(1, 256)
    for _ in range(60):  # bisection down to adjacent float32 values
        mid = _f32_midpoint(lo, hi)
        up = edi.to_uint8(mid) >= k
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    thr = hi.astype(np.float64)  # thr[k-1]: the first float32 rendered as >= k
    v0 = float(thr[0])
    scale = n_buckets / (float(thr[-1]) - v0)
    starts = v0 + np.arange(n_buckets) / scale
    bucket_u8 = np.searchsorted(thr, starts, side="right").astype(np.uint8)
    bucket_thr = np.full(n_buckets, np.inf)
    owner = np.minimum(((thr - v0) * scale).astype(np.int64), n_buckets - 1)
    inside = thr > starts[owner]
    bucket_thr[owner[inside]] = thr[inside]
    return v0, scale, bucket_u8, bucket_thr.astype(np.float32)


def _f32_midpoint(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A float32 strictly between a and b (a < b) when one exists, else a: bisection then stays put."""
    m = ((a.astype(np.float64) + b.astype(np.float64)) / 2).astype(np.float32)
    step = np.nextafter(a, b)
    return np.where((m > a) & (m < b), m, np.where(step < b, step, a)).astype(np.float32)


def _check_c(name: str, value: float | None) -> float | None:
    if value is None:
        return None
    v = float(value)
    if not (math.isfinite(v) and C_RANGE[0] <= v <= C_RANGE[1]):
        raise ConfigError(f"{name} must be a contrast threshold in [{C_RANGE[0]}, {C_RANGE[1]}] (got {value!r})")
    return v


class EdiReconstructor:
    """Deblurs each APS frame at mid-exposure and advances the latent image event by event."""

    def __init__(self, width: int, height: int, *, c: float | None = None, c_on: float | None = None,
                 c_off: float | None = None, estimator: str = contrast.DEFAULT_ESTIMATOR, reestimate_every: int = 0,
                 c_init: float = 0.2, history_pairs: int = 2, mask_hot_pixels: bool = True,
                 hot_min_rate_hz: float = 300.0, hot_rel_factor: float = 10.0, hot_decay: float = 0.8,
                 saturation: float | None = None, sample_pixels: int = 4000, denoise_us: int = 0,
                 estimator_options: dict | None = None, fit_patience: int = 2, fit_strong: float = 3.0,
                 c_history: int = 3) -> None:
        if width <= 0 or height <= 0:
            raise ConfigError(f"sensor size must be positive (got {width}x{height})")
        if reestimate_every < 0:
            raise ConfigError(f"reestimate_every must be >= 0 (got {reestimate_every})")
        self.width, self.height = int(width), int(height)
        c, c_on, c_off = _check_c("c", c), _check_c("c_on", c_on), _check_c("c_off", c_off)
        if (c_on is None) != (c_off is None) and c is None:
            raise ConfigError("give both c_on and c_off (or a single c)")
        self._fixed = c is not None or c_on is not None
        self.c_on = c_on if c_on is not None else (c if c is not None else _check_c("c_init", c_init))
        self.c_off = c_off if c_off is not None else (c if c is not None else self.c_on)
        if self._fixed:
            self._estimator: contrast.ContrastEstimator = contrast.FixedContrast(self.c_on, self.c_off)
        else:
            try:
                self._estimator = contrast.make_estimator(estimator, **(estimator_options or {}))
            except (ValueError, TypeError) as exc:
                raise ConfigError(str(exc)) from None
        self.reestimate_every = int(reestimate_every)
        self.reestimations = 0
        self._estimated = False
        self._frames_since_estimate = 0
        self._fit_fails = 0  # consecutive frames whose fit test failed
        self._startup_left = max(1, history_pairs) - 1  # start-up estimates after the first one
        self._still_votes = 0  # consecutive "events explain nothing" estimates not acted on yet
        self._fit_patience = int(fit_patience)
        self._fit_strong = float(fit_strong)
        self._c_history: collections.deque = collections.deque(maxlen=max(1, int(c_history)))
        self.ill_conditioned = 0  # estimates that were no information (flat cost curve): c kept
        self.last_fit: dict = {}  # the last frame's fit-test z, estimate and decision (for tools and stats)
        self._mask_hot = mask_hot_pixels
        self._hot_min_rate_hz = hot_min_rate_hz
        self._hot_rel = hot_rel_factor
        self._hot_decay = hot_decay
        self._saturation = saturation
        # background-activity filter: an event counts only if a neighbour fired within denoise_us before it
        self._denoise_us = int(denoise_us)
        self._activity = edi.new_activity_map(self.width, self.height) if self._denoise_us > 0 else None
        npix = self.width * self.height
        self._hot_counts = np.zeros(npix, np.float64)
        self._frame_counts = np.zeros(npix, np.int64)  # this exposure's events per pixel (numba path; kept zeroed)
        self._hot_duration_us = 0.0
        self._hot = np.zeros((self.height, self.width), bool)
        # c is estimated on a fixed random pixel sample: every c evaluation and the tables it needs stay small
        self._not_sample = np.ones(npix, bool)
        keep = np.random.default_rng(20190616).choice(npix, min(npix, int(sample_pixels)), replace=False)
        self._not_sample[keep] = False
        self._not_sample = self._not_sample.reshape(self.height, self.width)
        self._log_ref = np.zeros((self.height, self.width), np.float32)
        self._log_lat = np.zeros((self.height, self.width), np.float32)
        self._display = np.zeros((self.height, self.width), np.uint8)
        self._acc = (np.zeros(npix, np.int64), np.zeros(npix, np.int64))  # ON/OFF applied since f
        self._prev: contrast.FrameData | None = None
        self._pairs: collections.deque = collections.deque(maxlen=max(1, history_pairs))
        self.has_reference = False
        self.events_ignored = False  # set when the c estimator finds that the events carry no signal
        self._ref_t = 0
        self._exposure = (0, 0)
        self._t_last = -(2**63)
        self._pending_events = 0
        self._arrival_ns = 0
        self._streamer = False  # a streaming_copy(): its applied events are replayed into the original later
        self.frames = 0
        self.events_applied = 0
        self.last_deblur_ms = 0.0
        self.last_estimate_ms = 0.0

    # ---- public API ----

    @property
    def hot_pixels(self) -> int:
        return int(self._hot.sum())

    @property
    def hot_pixel_mask(self) -> np.ndarray:
        return self._hot.copy()

    def mark_gap(self) -> None:
        """Data were lost: the next frame is not compared with the previous one (no consistency across a gap).
        A no-op on a streaming_copy(): the caller hands the gap to the original, which owns the pairs."""
        if self._streamer:
            return
        self._prev = None
        self._pairs.clear()

    def streaming_copy(self) -> "EdiReconstructor":
        """A copy that can stream latent frames (on_events, render) from the current reference while this one
        deblurs the next APS frame on another thread. Only the latent state (image, display, denoise activity) is
        copied: ~30 µs at 346x260, where a deepcopy takes ~2 ms. The rest is shared: of it the copy reads only the
        hot-pixel mask and the reference, which the original replaces rather than changes in place. The copy keeps
        no c-estimation counts, since the events it applies are handed to this reconstructor's on_events
        afterwards anyway, and it ignores mark_gap() (the original must get it)."""
        twin = copy.copy(self)
        twin._log_lat = self._log_lat.copy()
        twin._display = self._display.copy()
        twin._pairs = collections.deque(maxlen=self._pairs.maxlen)  # never shared with the deblurring original
        if self._activity is not None:
            twin._activity = self._activity.copy()
        twin._streamer = True
        return twin

    def on_frame(self, frame: Frame, events: np.ndarray, arrival_ns: int = 0) -> Reconstruction:
        if self._streamer:
            raise NodeError("on_frame() on a streaming_copy(): deblur on the original reconstructor")
        t_start = time.perf_counter()
        img = frame.image
        if img.shape != (self.height, self.width):
            raise ConfigError(f"APS frame is {img.shape[1]}x{img.shape[0]} but the reconstructor was set up for "
                              f"{self.width}x{self.height}; check the source resolution")
        ts, te = int(frame.exposure_start_us), int(frame.exposure_end_us)
        f = frame.mid_exposure_us
        if self.has_reference and f <= self._ref_t:
            self.mark_gap()  # time went backwards (new recording, loop without offset): start over
        mask = self._hot if self._mask_hot else None
        t_all = events["t"]
        n_new = t_all.size - edi.time_index(t_all, self._t_last, "right")
        t_batch_end = int(t_all[-1]) if t_all.size else self._t_last
        if self._activity is not None:
            # the filter state sees the events it has not seen yet; this frame uses only the events that have a
            # neighbour event within denoise_us before or after them (isolated ones are most likely noise)
            fresh = events[edi.time_index(events["t"], self._t_last, "right"):]
            edi.background_activity_keep(fresh, self.width, self.height, self._activity, self._denoise_us)
            events = events[edi.supported_events_keep(events, self.width, self.height, self._denoise_us)]
        b = informative = None  # B as float: the estimators and the numpy path need it, the fused pass does not
        if not self._fixed:
            b, informative = edi.blurry_to_float(img, saturation=self._saturation)
            self._estimation_step(events, b, informative, ts, te, f, mask)
        frame_counts = None
        if self._mask_hot:
            frame_counts = self._frame_counts if edi._jit is not None else np.zeros(self.width * self.height,
                                                                                  np.int64)
        if not self._fixed:  # the accumulators are used (and written) only when c is estimated
            for a in self._acc:
                a.fill(0)
        divisor = edi.log_divisor_events(events, self.width, self.height, ts, te, f, self.c_on, self.c_off,
                                         mask=mask, event_counts=frame_counts,
                                         counts_after_f=None if self._fixed else self._acc)
        if self.events_ignored:  # still scene: L(f) = B and the latent image stays there
            divisor = (divisor[0][:0], divisor[1][:0], divisor[2][:0] if divisor[2] is not None else None)
        t = events["t"]
        pixels, _, delta_end = divisor
        fused = edi._jit is not None and img.dtype == np.uint8 and delta_end is not None
        if fused:
            # one numba pass: L(f), its uint8 image, the latent image at te and the display buffer
            deblurred = np.empty((self.height, self.width), np.uint8)
            self._log_ref = np.empty((self.height, self.width), np.float32)
            lut_log, lut_u8 = _u8_tables()
            sat = 255.0 if self._saturation is None else float(self._saturation)
            edi._jit.finish_frame_u8(np.ascontiguousarray(img).reshape(-1), sat, lut_log, lut_u8, pixels,
                                     divisor[1], delta_end, np.float32(edi.LOG_MIN), np.float32(edi.LOG_MAX),
                                     self._log_ref.reshape(-1), deblurred.reshape(-1), self._log_lat.reshape(-1),
                                     self._display.reshape(-1), *_render_buckets())
        else:
            if b is None:
                b, informative = edi.blurry_to_float(img, saturation=self._saturation)
            self._log_ref = edi.deblur_log(b, None, self.c_on, self.c_off, informative=informative,
                                           divisor=divisor)
            deblurred = edi.to_uint8(self._log_ref)
            # latent state: from L(f) through the events after f that are already here
            np.copyto(self._log_lat, self._log_ref)
        if delta_end is not None:  # the divisor pass already knows E(f -> te): jump there in O(pixels)
            if not fused:
                lat = self._log_lat.reshape(-1)
                lat[pixels] += delta_end.astype(np.float32)
                np.clip(lat, edi.LOG_MIN, edi.LOG_MAX, out=lat)
            # (the consistency pairs need the counts after f: the divisor pass added them to the accumulators)
            after = events[edi.time_index(t, te, "right"):]
        else:
            after = events[edi.time_index(t, f, "right"):]
        if self.events_ignored:
            edi.add_counts(after, self.width, self.height, *self._acc, mask=mask)
        else:  # the fused pass filled the display buffer already: only the touched pixels change
            edi.propagate_log(self._log_lat, after, self.c_on, self.c_off, mask=mask,
                              display=self._display if fused else None, counts=None if self._fixed else self._acc)
        if not fused:
            np.copyto(self._display, edi.to_uint8(self._log_lat))
        if frame_counts is not None:
            self._update_hot(frame_counts, te - ts)
        self.has_reference = True
        self._ref_t = f
        self._exposure = (ts, te)
        self._t_last = max(self._t_last, t_batch_end, f)
        self.frames += 1
        self.events_applied += n_new
        n_events = self._pending_events + n_new
        self._pending_events = 0
        self._arrival_ns = arrival_ns or self._arrival_ns
        self.last_deblur_ms = (time.perf_counter() - t_start) * 1e3
        return self._reconstruction(deblurred, f, "deblurred", n_events)

    def on_events(self, events: np.ndarray, arrival_ns: int = 0) -> None:
        if events.size == 0:
            return
        if not self.has_reference:
            return  # nothing to advance yet; the first APS frame rebuilds everything
        mask = self._hot if self._mask_hot else None
        n = int(events.size)
        t_end = int(events["t"][-1])
        if self._activity is not None:
            events = events[edi.background_activity_keep(events, self.width, self.height, self._activity,
                                                          self._denoise_us)]
        count = not (self._fixed or self._streamer)
        if self.events_ignored:  # keep counting for the next consistency check, but leave the image alone
            if count:
                edi.add_counts(events, self.width, self.height, *self._acc, mask=mask)
        else:
            edi.propagate_log(self._log_lat, events, self.c_on, self.c_off, mask=mask, display=self._display,
                              counts=self._acc if count else None)
        self._t_last = max(self._t_last, t_end)
        self._pending_events += n
        self.events_applied += n
        if arrival_ns:
            self._arrival_ns = arrival_ns

    def on_events_frames(self, events: np.ndarray, cuts: Sequence[int],
                         arrivals: Sequence[int]) -> list[Reconstruction]:
        """on_events(events), rendering a latent frame after the first cuts[k] events (increasing, within
        1..len(events)) and stamping it with arrivals[k]. The frames are those of on_events(piece, arrival) +
        render() per piece, but the kernel's arguments are set up once per batch, not once per frame (the
        streaming worker's hot path: ~5 µs of a ~25 µs frame)."""
        self._need_reference("on_events_frames()")
        if not cuts:
            self.on_events(events, 0)
            return []
        jit = edi._jit
        flat = self._log_lat.reshape(-1)
        if jit is None or self._activity is not None or self.events_ignored or flat.dtype != np.float32:
            return self._frames_one_by_one(events, cuts, arrivals)
        mask, use_mask = edi._mask_arg(self._hot if self._mask_hot else None)
        count = not (self._fixed or self._streamer)
        acc_on, acc_off = self._acc if count else (edi._NO_COUNTS, edi._NO_COUNTS)
        d_on, d_off = float(self.c_on), -float(self.c_off)
        disp = self._display.reshape(-1)
        w, h, lo, hi = self.width, self.height, edi.LOG_MIN, edi.LOG_MAX
        x, y, p, t = events["x"], events["y"], events["p"], events["t"]
        out = []
        i0 = 0
        for i1, arrival in zip(cuts, arrivals):
            jit.propagate(x[i0:i1], y[i0:i1], p[i0:i1], w, h, mask, use_mask, flat, d_on, d_off, lo, hi, disp, True,
                          1.0, acc_on, acc_off, count)
            if arrival:
                self._arrival_ns = arrival
            out.append(self._reconstruction(self._display.copy(), int(t[i1 - 1]), "latent",
                                            self._pending_events + i1 - i0))
            self._pending_events = 0
            i0 = i1
        n = int(events.size)
        if i0 < n:
            jit.propagate(x[i0:], y[i0:], p[i0:], w, h, mask, use_mask, flat, d_on, d_off, lo, hi, disp, True, 1.0,
                          acc_on, acc_off, count)
            self._pending_events += n - i0
        self._t_last = max(self._t_last, int(t[-1]))
        self.events_applied += n
        return out

    def _frames_one_by_one(self, events: np.ndarray, cuts: Sequence[int], arrivals: Sequence[int]) -> list:
        out = []
        i0 = 0
        for i1, arrival in zip(cuts, arrivals):
            self.on_events(events[i0:i1], arrival)
            out.append(self.render())
            i0 = i1
        self.on_events(events[i0:], 0)
        return out

    def render(self) -> Reconstruction:
        self._need_reference("render()")
        n = self._pending_events
        self._pending_events = 0
        return self._reconstruction(self._display.copy(), self._t_last, "latent", n)

    def render_from_reference(self, t_us: int, events: np.ndarray) -> Reconstruction:
        """Latent at t from the current L(f), using the events between t and f (t may be before f)."""
        self._need_reference("render_from_reference()")
        t_us = int(t_us)
        f = self._ref_t
        mask = self._hot if self._mask_hot else None
        if t_us >= f:
            delta = edi.event_delta(events, self.width, self.height, self.c_on, self.c_off, t0=f + 1, t1=t_us,
                                    mask=mask)
        else:
            delta = -edi.event_delta(events, self.width, self.height, self.c_on, self.c_off, t0=t_us + 1, t1=f,
                                     mask=mask)
        if self.events_ignored:
            delta = 0.0
        log_l = np.clip(self._log_ref + delta, edi.LOG_MIN, edi.LOG_MAX)
        return self._reconstruction(edi.to_uint8(log_l), t_us, "latent", int(events.size))

    def stats(self) -> dict:
        return {
            "c_on": self.c_on, "c_off": self.c_off, "c_fixed": self._fixed, "estimator": self._estimator.name,
            "reestimations": self.reestimations, "ill_conditioned": self.ill_conditioned,
            "hot_pixels": self.hot_pixels, "frames": self.frames,
            "events_ignored": self.events_ignored,
            "events_applied": self.events_applied, "has_reference": self.has_reference,
            "last_deblur_ms": round(self.last_deblur_ms, 3), "last_estimate_ms": round(self.last_estimate_ms, 3),
        }

    # ---- internals ----

    def _need_reference(self, what: str) -> None:
        if not self.has_reference:
            raise NodeError(f"{what} called before the first APS frame was deblurred (check has_reference first)")

    def _reconstruction(self, image: np.ndarray, t_us: int, kind: str, n_events: int) -> Reconstruction:
        return Reconstruction(image=image, t_us=int(t_us), kind=kind, ref_t_us=int(self._ref_t),
                              exposure_start_us=self._exposure[0], exposure_end_us=self._exposure[1],
                              c_on=float(self.c_on), c_off=float(self.c_off), n_events=int(n_events),
                              arrival_ns=int(self._arrival_ns))

    def _counts_between(self, events: np.ndarray, f: int) -> tuple[np.ndarray, np.ndarray]:
        """ON/OFF counts per pixel from the previous f to this f, without counting any event twice: the
        accumulator holds what was applied after the previous f (up to t_last); this batch may overlap it."""
        n_on, n_off = self._acc[0].copy(), self._acc[1].copy()
        mask = self._hot if self._mask_hot else None
        t0, t1, sign = self._count_range(f)
        if t1 >= t0:
            edi.add_counts(events, self.width, self.height, n_on, n_off, t0=t0, t1=t1, mask=mask, sign=sign)
        np.maximum(n_on, 0, out=n_on)
        np.maximum(n_off, 0, out=n_off)
        return n_on, n_off

    def _count_range(self, f: int) -> tuple[int, int, int]:
        """(t0, t1, sign): the events with t0 <= t <= t1 to add (sign 1) to or take off (sign -1) the
        accumulator to get the counts from the previous f to f; t1 < t0 when there are none."""
        t_last = self._t_last
        if f < t_last:  # applied events after this f do not belong to the interval
            return f + 1, t_last, -1
        if f > t_last:  # events up to this f that were not applied yet
            return t_last + 1, f, 1
        return 1, 0, 1

    def _sample_and_counts(self, events: np.ndarray, excluded: np.ndarray, ts: int, te: int, f: int,
                           hot: np.ndarray | None) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """The sample's events in [ts, te] and the counts of _counts_between, in one numba pass."""
        t = events["t"]
        s0, s1 = edi.time_index(t, ts, "left"), edi.time_index(t, te, "right")
        t0, t1, sign = self._count_range(f)
        c0, c1 = (edi.time_index(t, t0, "left"), edi.time_index(t, t1, "right")) if t1 >= t0 else (s0, s0)
        c1 = max(c0, c1)
        n_on, n_off = self._acc[0].copy(), self._acc[1].copy()
        keep = (~excluded).reshape(-1).view(np.uint8)
        m, use_m = edi._mask_arg(hot)
        idx = edi._jit.select_and_count(events["x"], events["y"], events["p"], self.width, self.height, keep, s0, s1,
                                        m, use_m, n_on, n_off, c0, c1, sign)
        np.maximum(n_on, 0, out=n_on)
        np.maximum(n_off, 0, out=n_off)
        return events[idx], (n_on, n_off)

    def _estimation_step(self, events: np.ndarray, b: np.ndarray, informative: np.ndarray, ts: int, te: int,
                         f: int, hot: np.ndarray | None) -> None:
        """Level table of this frame (on the pixel sample unless the estimator needs the whole image), the pair
        with the previous frame, then c: kept if it still fits, re-estimated otherwise (or when due)."""
        full = getattr(self._estimator, "needs_full_image", False)
        excluded = self._not_sample if hot is None else (self._not_sample | hot)
        pair_due = self._prev is not None and self.has_reference
        counts = None
        if full:
            table = edi.build_level_table(events, self.width, self.height, ts, te, f, mask=hot,
                                          segments=self._estimator.separate)
        else:  # the sample's events first (one cheap pass), so the table build touches only them
            if counts is None and pair_due and edi._jit is not None and ts < te:
                sample, counts = self._sample_and_counts(events, excluded, ts, te, f, hot)  # one pass for both
            else:
                sample = edi.events_at_pixels(events, self.width, self.height, ~excluded, ts, te)
            table = edi.build_level_table(sample, self.width, self.height, ts, te, f,
                                          segments=self._estimator.separate)
        em = None
        if full:
            em = contrast.event_map(events, self.width, self.height, f, ts, te, 0.25 * max(te - ts, 1))
        cur = contrast.FrameData(b, informative, table, em)
        if pair_due:
            n_on, n_off = counts if counts is not None else self._counts_between(events, f)
            self._pairs.append(contrast.FramePair(self._prev, cur, n_on, n_off, excluded.reshape(-1)))
        self._choose_c(cur)
        self._prev = cur

    def _choose_c(self, cur: contrast.FrameData) -> None:
        """Cached c: re-estimate when due (start-up, every K frames) or when the fit test fails clearly (by
        `fit_z` standard errors of the cost difference on `fit_patience` consecutive frames, or by
        `fit_strong` x fit_z once). An estimate whose cost curve is flat is no information: c stays. An accepted
        estimate enters a short history and c becomes its median, so one odd frame pair does not move c."""
        if self._fixed:
            return
        pairs = list(self._pairs)
        if self._estimator.needs_pair and not pairs:
            return
        self._frames_since_estimate += 1
        t0 = time.perf_counter()
        # start-up: estimate until the pair history is full (the first estimate sees a single pair)
        startup = self._estimated and self._startup_left > 0 and len(pairs) >= 2
        if startup:
            self._startup_left -= 1
        first = not self._estimated
        floor = getattr(self._estimator, "c_min", 0.0)
        info: dict = {}
        if self._still_votes:  # a still verdict after start-up waits for the next frame's pair (cheap check)
            self._still_votes = 0
            z = self._estimator.compare(pairs[-1:], (self.c_on, self.c_off), [(floor, floor)])
            info["still_z"] = float("nan") if z is None else z
            if z is not None and z >= self._estimator.fit_z:
                self.events_ignored = True
                info["decision"] = "still"
            return self._done(info, t0)
        due = first or startup or bool(self.reestimate_every and
                                       self._frames_since_estimate >= self.reestimate_every)
        if not due:
            probe = (floor, floor) if self.events_ignored else (self.c_on, self.c_off)
            score = getattr(self._estimator, "fit_score", None)
            if score is None:
                due = not self._estimator.fits(cur, pairs[-1:], probe)
            else:
                if self.events_ignored:  # still scene: do the events now explain more at the cached c than at none?
                    z = self._estimator.compare(pairs[-1:], probe, [(self.c_on, self.c_off)])
                else:
                    z = score(pairs[-1:], probe)
                fit_z = self._estimator.fit_z
                fail = z is not None and z >= fit_z
                self._fit_fails = self._fit_fails + 1 if fail else 0
                due = fail and (self._fit_fails >= self._fit_patience or z >= self._fit_strong * fit_z)
                info["fit_z"] = float("nan") if z is None else z
        if due:
            found = self._estimator.estimate(cur, pairs, (self.c_on, self.c_off))
            if found is not None:
                info["found"] = float(found[0])
                self._estimated = True
                self.reestimations += 1
                self._frames_since_estimate = 0
                self._fit_fails = 0
                # a fit at the bottom of the search range means the events do not explain the brightness
                # changes between frames (noise on a still scene): then no event is applied at all
                if floor > 0 and max(found) <= 1.25 * floor:
                    # believed at start-up; later the next frame's pair must agree (a pair across a cut in the
                    # scene also looks as if the events explained nothing)
                    if first or self.events_ignored or not hasattr(self._estimator, "compare"):
                        self.events_ignored = True
                        info["decision"] = "still"
                    else:
                        self._still_votes = 1
                        info["decision"] = "still?"
                    return self._done(info, t0)
                inform = getattr(self._estimator, "information", None)
                z_info = inform(pairs, found) if inform is not None else None
                info["info_z"] = float("nan") if z_info is None else z_info
                if z_info is not None and z_info < self._estimator.info_z:
                    info["decision"] = "flat"  # keep the cached c (and whether events are applied)
                    self.ill_conditioned += 1
                else:
                    self.events_ignored = False
                    if startup:  # this estimate saw more pairs than the first one: it supersedes it
                        self._c_history.clear()
                    self._c_history.append(tuple(min(max(v, C_RANGE[0]), C_RANGE[1]) for v in found))
                    self.c_on, self.c_off = (float(np.median(v)) for v in zip(*self._c_history))
                    info["decision"] = "update"
        self._done(info, t0)

    def _done(self, info: dict, t0: float) -> None:
        self.last_fit = info
        self.last_estimate_ms = (time.perf_counter() - t0) * 1e3

    def _update_hot(self, frame_counts: np.ndarray, exposure_us: int) -> None:
        """Decaying per-pixel event counts over past exposures -> hot-pixel mask used from the next frame on."""
        if edi._jit is not None and frame_counts is self._frame_counts:  # one pass, no temporaries; resets counts
            self._hot_duration_us = self._hot_duration_us * self._hot_decay + exposure_us
            self._hot = np.empty((self.height, self.width), bool)  # a new array: hot_pixel_mask hands out copies
            edi._jit.update_hot(self._hot_counts, frame_counts, float(self._hot_decay), float(self._hot_duration_us),
                                float(self._hot_min_rate_hz), float(self._hot_rel), self._hot.reshape(-1))
            return
        self._hot_counts *= self._hot_decay
        self._hot_counts += frame_counts
        self._hot_duration_us = self._hot_duration_us * self._hot_decay + exposure_us
        self._hot = edi.hot_pixel_mask(self._hot_counts, self._hot_duration_us, min_rate_hz=self._hot_min_rate_hz,
                                       rel_factor=self._hot_rel).reshape(self.height, self.width)
