"""A live quality figure that needs no ground truth: how well the node's own output predicted each APS frame.

Owns the per-APS-frame prediction score and its running summaries. No threads, no I/O. The worker
owns one `PredictionScore` and calls it on its own thread: `on_events(events)` for every event chunk it reads,
`on_aps_frame(frame)` when it takes an APS frame from the ring, `on_emitted(rec)` for every Reconstruction it
sends. `stats()` may be called from any thread (it returns a copy of a dict replaced, never changed, in place).

Definition, for every APS frame k+1 (window W = [exposure_start, exposure_end] of k+1, B = 8-bit scale):

- Honest frames: emitted Reconstructions whose reference is an earlier APS frame, `ref_t_us < mid-exposure of
  k+1`. Frame k+1's own deblurred frame and every latent frame rendered from it have ref_t_us = its mid-exposure
  and are excluded, so nothing fitted on B_{k+1} is scored against it.
- Prediction P: the time average over W of the honest frames, each held from its `t_us` until the next honest
  frame's `t_us` (piecewise constant; the frame in force at exposure_start counts from exposure_start; frames
  are ordered by t_us, a later emission wins a tie). Linear intensity: the uint8 images exactly as emitted,
  weighted by hold time in µs in exact integer arithmetic, then one division (a constant output gives P equal
  to that output, bit for bit). A zero-length window takes the frame in force at its start.
- Scored only when an honest frame is in force at exposure_start (coverage 1). Otherwise (start of a stream,
  after a reset, frames lost to the memory cap) the frame is reported unscored: a prediction of part of the
  exposure is not a prediction of B. A window with one held frame (the node sent nothing new during the
  exposure) is scored: that is what a viewer showed. `n_frames_used` tells the two apart.
- psnr_pred = PSNR(P, B_{k+1}); psnr_still = PSNR(B_k, B_{k+1}), the no-motion baseline, B_k the previous APS
  frame. PSNR = 10 log10(255^2 / MSE), capped at PSNR_CAP_DB (an exact prediction reports the cap, not inf).
- Pixels: those where B_{k+1} is informative, i.e. not clipped (0 < B < saturation; default full scale of the
  dtype), the node's own rule for which APS values it may divide by. A clipped target is only a bound on the
  truth. Both figures use the same pixels. No informative pixel: the frame is unscored (never NaN).
- Active pixels: those that fired at least one event among the events fed since the previous APS frame was
  taken, i.e. (exposure_end of k, exposure_end of k+1]: the changes that make B_{k+1} differ from B_k (the
  readout gap included), chosen by the events alone, not by the target nor by the predictor, so both figures
  are compared on the same fair set. None when no event was fed or no active pixel is informative.
- Modes: on in "causal" only. In "nearest" the frames inside k+1's exposure are rendered from k+1 itself,
  so the honest subset would be a stale held frame that is not what the node sent: the figure is off
  (stats report pred_enabled False and no values). "fused" is off likewise: each of its frames is fitted on
  the next APS frame as well.
- Held frames: APS frame k+1 is not scored when the node sent no frame since it took frame k (a still scene:
  the static-scene policy sends nothing but the heartbeat). The viewer kept showing what it had, so the score
  would only repeat how still the scene is, at the cost of a conversion and four MSEs per APS frame (most of a
  still camera's CPU budget). Such frames are counted in `pred_frames_held`; the means describe the APS frames
  during which the node sent something (at least one frame since the previous APS frame). `score_every` counts
  the frames that are not held.
- Completion: frame k+1 is scored when the node sends a frame with ref_t_us >= its mid-exposure or with
  t_us > its exposure end (in causal order no honest frame for it can follow), when the next APS frame
  arrives, or at finish(). So calling on_aps_frame before or after the frame's own deblur is both fine.

Cost: storing an emitted frame keeps a reference (no copy; receivers never modify emitted images). Each frame
is integrated at most once per window it overlaps (one compiled int32 multiply-add over the pixels,
edi_live.hold_average); frames outside every window (readout gaps) cost nothing. Per APS frame: one copy of B,
four masked MSEs. on_events: O(events), one compiled pass.
A held APS frame costs no arithmetic on its pixels (converted only if a later window needs it as B_k).
Memory: the frames since the oldest window that may still need them, at most `max_frames`.
"""

from __future__ import annotations

import bisect
import collections
import math
import statistics
from dataclasses import dataclass
from typing import Any

import numpy as np

import edi_live.edi as edi
from edi_live.datatypes import ColorFilter, Frame, Reconstruction
from edi_live.hold_average import hold_average
from edi_live.psnr import PSNR_CAP_DB, psnr_pair, to_8bit_scale

SCORED_MODES = ("causal",)
_NEVER = 2**63  # a time no frame reaches


@dataclass(frozen=True, slots=True)
class PredictionResult:
    """The score of one APS frame (k+1). PSNR values in dB, None when undefined (see the module docstring)."""

    seq: int
    t_us: int  # mid-exposure of frame k+1
    exposure_start_us: int
    exposure_end_us: int
    psnr_pred_db: float | None
    psnr_still_db: float | None
    psnr_pred_active_db: float | None
    psnr_still_active_db: float | None
    n_frames_used: int
    coverage: float  # fraction of the exposure with an honest frame in force
    valid_px: int  # informative pixels of B_{k+1}
    active_px: int  # informative pixels that had events

    @property
    def scored(self) -> bool:
        return self.psnr_pred_db is not None


@dataclass(slots=True)
class _Window:
    seq: int
    start: int
    end: int
    mid: int
    target: np.ndarray  # B_{k+1}, float32, 8-bit scale
    still: np.ndarray  # B_k, float32, 8-bit scale
    valid: np.ndarray  # bool
    active: np.ndarray | None  # bool, events since the previous APS frame


_UNMARKED_MAX = 1 << 18  # events held unmarked at most, 4 MB (no APS frame nor frame sent for that long)


class PredictionScore:
    """Scores each APS frame by how well the node's earlier output predicted it (module docstring)."""

    def __init__(self, mode: str = "causal", *, window: int = 100, saturation: float | None = None,
                 max_frames: int = 2000, score_every: int = 1, color_filter: ColorFilter | None = None,
                 gray: bool = False) -> None:
        self.enabled = mode in SCORED_MODES
        # a colour source's APS frames are compared as the node shows them (demosaiced, or grey with `gray`)
        self._color_filter, self._gray = color_filter, gray
        self._score_every = max(1, int(score_every))  # score one APS frame in N (the others cost nothing)
        self._aps_seen = 0
        self.mode = mode
        self._saturation = saturation
        self._max_frames = max(2, int(max_frames))
        self._recent: collections.deque[PredictionResult] = collections.deque(maxlen=max(1, int(window)))
        self.results_total = 0
        self.scored_total = 0
        self.frames_dropped = 0  # emitted frames dropped by the memory cap
        self.held_total = 0  # APS frames not scored: nothing was sent since the previous one (docstring)
        self.last: PredictionResult | None = None
        self.last_prediction: np.ndarray | None = None  # the last scored frame's prediction P (float64, 8-bit scale)
        self._summary: dict[str, Any] = self._summarise()
        self.reset()

    # ---------------------------------------------------------------- feeding (worker thread)

    def reset(self) -> None:
        """Forget the stream (time went backwards, new recording). Results and totals are kept."""
        self._t: list[int] = []  # held frames, sorted by t_us
        self._ref: list[int] = []
        self._img: list[np.ndarray] = []
        self._set_pending([])
        self._prev_b: np.ndarray | None = None  # B_k on the 8-bit scale (converted when first needed)
        self._prev_image: np.ndarray | None = None  # ... and as taken
        self._sent_since_aps = False
        self._prev_end: int | None = None
        self._prev_mid: int | None = None
        self._exposures: collections.deque[int] = collections.deque(maxlen=8)
        self._shape: tuple[int, ...] | None = None
        self._black, self._gamma = 0.0, 1.0  # the APS response of the latest frame sent (undone in the frames)
        self._events_map: np.ndarray | None = None  # flat bool: pixels with events since the last APS frame
        self._events_fed = self._marked = False
        self._unmarked: list[np.ndarray] = []  # not marked yet: nothing sent, the next APS frame may not be scored
        self._unmarked_n = 0  # events in them
        self._last_ref = self._last_t = self._t_max = -(2**63)
        self._pruned_at = 0

    def on_events(self, events: np.ndarray) -> None:
        """Events as the worker reads them (time order). Before the first APS frame they are ignored."""
        if not self.enabled or self._events_map is None or len(events) == 0:
            return
        self._events_fed = True
        if (self._aps_seen + 1) % self._score_every:
            return  # the next APS frame is not scored: which pixels fired before it is never read
        self._unmarked.append(events)  # (a still scene's reads then mark nothing: ~20 us each, mostly cache misses)
        self._unmarked_n += len(events)
        if self._sent_since_aps or self._unmarked_n > _UNMARKED_MAX:
            self._mark_unmarked()

    def _mark_unmarked(self) -> None:
        h, w = self._shape[:2]
        for events in self._unmarked:  # off-sensor events: ignored, not marked elsewhere
            edi.mark_event_pixels(events, w, h, self._events_map)
        self._unmarked, self._unmarked_n, self._marked = [], 0, True

    def on_aps_frame(self, frame: Frame) -> list[PredictionResult]:
        """An APS frame taken by the worker. Returns the results this completes (earlier frames' scores)."""
        if not self.enabled:
            return []
        image = self._as_output_layout(frame)
        shape = image.shape
        mid = frame.mid_exposure_us
        if self._shape != shape or (self._prev_mid is not None and mid <= self._prev_mid):
            out = self._complete_all()
            self.reset()
            self._shape = shape
        else:
            out = self._complete_all()  # every earlier window is complete once a later APS frame is taken
        held = self._prev_image is not None and not self._sent_since_aps
        self.held_total += held
        self._aps_seen += not held
        if self._prev_image is not None and not held and self._aps_seen % self._score_every == 0:
            target, valid = to_8bit_scale(image, self._saturation)
            if self._prev_b is None:
                self._prev_b = to_8bit_scale(self._prev_image, self._saturation)[0]
            active = None
            if self._events_fed:
                active = self._events_map.reshape(shape[:2])
                if len(shape) == 3:  # an event marks all three colours of its pixel in the demosaiced frame
                    active = np.repeat(active[..., None], shape[2], axis=2)
            self._set_pending(self._pending + [_Window(frame.seq, frame.exposure_start_us, frame.exposure_end_us, mid,
                                                       target, self._prev_b, valid, active)])
            self._prev_b = target
        else:
            self._prev_b = None
        if self._marked or self._events_map is None:
            self._events_map = np.zeros(shape[0] * shape[1], bool)
        self._events_fed = self._marked = self._sent_since_aps = False
        self._unmarked, self._unmarked_n = [], 0
        self._prev_image, self._prev_end, self._prev_mid = image, frame.exposure_end_us, mid
        self._exposures.append(frame.exposure_us)
        out.extend(self._complete(self._last_ref, self._last_t))  # the node may already have moved past it
        self._prune()
        return out

    def _as_output_layout(self, frame: Frame) -> np.ndarray:
        """The APS frame in the layout of the node's output: as it is for a grey sensor; for a colour one
        demosaiced to BGR, or grey with `gray`, as the reconstructor shows its mosaic."""
        if self._color_filter is None and frame.color_filter is None and frame.image.ndim == 2:
            return frame.image
        from edi_live.colour_edi import aps_as_output  # OpenCV: loaded for colour sources only

        return aps_as_output(frame, self._color_filter, self._gray)

    def on_emitted(self, rec: Reconstruction) -> list[PredictionResult]:
        """A frame the node sent, in emission order. Returns the results it completes."""
        image = rec.image
        if not self.enabled or (self._shape is not None and image.shape != self._shape):
            return []  # not an image of this sensor's APS layout: nothing it could predict
        # called for every frame sent (~20k a second at the sensor's rate): the common case appends, in time order
        t, ref = rec.t_us, rec.ref_t_us
        if not self._t or t >= self._t[-1]:
            self._t.append(t)
            self._ref.append(ref)
            self._img.append(image)
        else:
            i = bisect.bisect_right(self._t, t)
            self._t.insert(i, t)
            self._ref.insert(i, ref)
            self._img.insert(i, image)
        self._black, self._gamma = rec.black_level, rec.aps_gamma
        self._last_ref, self._last_t = ref, t
        self._sent_since_aps = True
        if self._unmarked:  # the next APS frame is scored: the pixels with events count
            self._mark_unmarked()
        if t > self._t_max:
            self._t_max = t
        out = self._complete(ref, t) if ref >= self._due_mid or t > self._due_end else []
        if len(self._t) >= 2 * self._pruned_at + 16:
            self._prune()
        return out

    def finish(self) -> list[PredictionResult]:
        """End of the stream: score what is pending (every frame the node will send was sent)."""
        return self._complete_all() if self.enabled else []

    # ---------------------------------------------------------------- reading (any thread)

    def stats(self) -> dict[str, Any]:
        """Flat summary of the last `window` scored APS frames (means in dB unless named otherwise)."""
        return {**self._summary, "pred_frames_held": self.held_total}

    # ---------------------------------------------------------------- internals

    def _complete(self, ref: int, t: int) -> list[PredictionResult]:
        done = [w for w in self._pending if ref >= w.mid or t > w.end]
        if not done:
            return []
        self._set_pending([w for w in self._pending if not (ref >= w.mid or t > w.end)])
        return [self._score(w) for w in done]

    def _set_pending(self, windows: list[_Window]) -> None:
        """The windows still to score, and the earliest mid-exposure and end among them: on_emitted looks at the
        windows only once a frame reaches one of those."""
        self._pending = windows
        self._due_mid = min((w.mid for w in windows), default=_NEVER)
        self._due_end = min((w.end for w in windows), default=_NEVER)

    def _complete_all(self) -> list[PredictionResult]:
        done = self._pending
        self._set_pending([])
        return [self._score(w) for w in done]

    def _integrate(self, w: _Window) -> tuple[np.ndarray | None, int, float]:
        """(time average of the honest frames over the window or None, frames used, coverage)."""
        honest = [i for i in range(len(self._t)) if self._ref[i] < w.mid]
        times = [self._t[i] for i in honest]
        first = bisect.bisect_right(times, w.start) - 1  # the honest frame in force at the window start
        if first < 0:
            covered = sum(max(0, min(b, w.end) - max(a, w.start))
                          for a, b in zip(times, times[1:] + [w.end]))
            span = w.end - w.start
            return None, 0, (covered / span if span > 0 else 0.0)
        if w.end == w.start:
            return self._img[honest[first]].astype(np.float64), 1, 1.0
        images, holds = [], []
        for j in range(first, len(honest)):
            a = max(times[j], w.start)
            if a >= w.end and j > first:
                break
            b = min(times[j + 1], w.end) if j + 1 < len(honest) else w.end
            if b > a:
                images.append(self._img[honest[j]])
                holds.append(b - a)
        return hold_average(images, holds, w.end - w.start), len(images), 1.0

    def _score(self, w: _Window) -> PredictionResult:
        prediction, used, coverage = self._integrate(w)
        valid_px = int(np.count_nonzero(w.valid))
        active_idx = None if w.active is None else np.flatnonzero(w.active & w.valid)
        active_px = 0 if active_idx is None else int(active_idx.size)
        pred = still = pred_a = still_a = None
        if prediction is not None and valid_px:
            if self._black or self._gamma != 1.0:  # the frames are linear: encode them as the APS would
                prediction = np.float32(self._black) + np.float32(255.0) * (
                    prediction / np.float32(255.0)) ** np.float32(1.0 / self._gamma)
            pred, pred_a = psnr_pair(prediction, w.target, w.valid, valid_px, active_idx)
            still, still_a = psnr_pair(w.still, w.target, w.valid, valid_px, active_idx)
            self.last_prediction = prediction
        result = PredictionResult(w.seq, w.mid, w.start, w.end, pred, still, pred_a, still_a, used, coverage,
                                  valid_px, active_px)
        self.results_total += 1
        self.last = result
        if result.scored:
            self.scored_total += 1
            self._recent.append(result)
        self._summary = self._summarise()
        return result

    def _prune(self) -> None:
        """Drop frames no window can need: before the frame in force at the oldest start still to come."""
        n = len(self._t)
        keep = n
        for w in self._pending:
            honest_before = [i for i in range(n) if self._ref[i] < w.mid and self._t[i] <= w.start]
            keep = min(keep, honest_before[-1] if honest_before else 0)
        if self._prev_end is not None and self._exposures:
            # a later APS frame ends after every frame sent so far and starts after this one's exposure end
            horizon = max(self._prev_end, self._t_max - 2 * max(self._exposures))
            keep = min(keep, max(0, bisect.bisect_right(self._t, horizon) - 1))
        else:
            keep = 0
        keep = max(keep, n - self._max_frames)
        if n - self._max_frames > 0 and keep == n - self._max_frames:
            self.frames_dropped += n - self._max_frames
        if keep > 0:
            del self._t[:keep], self._ref[:keep], self._img[:keep]
        self._pruned_at = len(self._t)

    def _summarise(self) -> dict[str, Any]:
        recent = list(self._recent)
        pred = [r.psnr_pred_db for r in recent]
        still = [r.psnr_still_db for r in recent]
        act = [(r.psnr_pred_active_db, r.psnr_still_active_db) for r in recent if r.psnr_pred_active_db is not None]

        def mean(v: list) -> float | None:  # plain Python: numpy's per-call overhead was ~0.3 ms per summary
            return round(math.fsum(v) / len(v), 3) if v else None

        def median(v: list) -> float | None:
            return round(statistics.median(v), 3) if v else None

        return {
            "pred_enabled": self.enabled,
            "pred_psnr_db": mean(pred), "still_psnr_db": mean(still),
            "pred_gain_db": mean([p - s for p, s in zip(pred, still)]),
            "pred_psnr_median_db": median(pred), "still_psnr_median_db": median(still),
            "pred_psnr_active_db": mean([a[0] for a in act]),
            "still_psnr_active_db": mean([a[1] for a in act]),
            "pred_beats_still_frac": round(sum(p > s for p, s in zip(pred, still)) / len(pred), 3) if pred else None,
            "pred_frames_scored": self.scored_total,
            "pred_frames_unscored": self.results_total - self.scored_total,
        }
