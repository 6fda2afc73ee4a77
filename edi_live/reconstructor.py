"""EdiReconstructor: the EDI core's state machine, the one Reconstructor (edi_live.reconstruction) of the node.

Per APS frame it filters the events it trusts (pixel_masks), deblurs L(f) with the c in force and restarts the
latent image there (latent_state); between frames it advances the latent image event by event. The c, black level
and clock offset policies re-calibrate from the frames (frame_calibration); what can wait for the deblurred frame
to leave runs in settle(), and takes effect at the next frame. Knobs: one frozen ReconstructorSettings. Runs on
one thread at a time (not thread-safe). Time: see reconstruction.py.
"""

from __future__ import annotations

import copy
import time
from typing import Any, Callable, Sequence

import numpy as np

import edi_live.colour_edi as colour_edi
import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.datatypes import Frame, Reconstruction
from edi_live.errors import ConfigError, NodeError
from edi_live.exposure_ahead import ExposureAhead
from edi_live.flicker_pixels import FlickerPixels
from edi_live.frame_calibration import FrameCalibration
from edi_live.latent_state import LatentState
from edi_live.pixel_masks import combined_mask
from edi_live.reconstructor_parts import build_calibration, build_masks, build_noise, resolve_settings
from edi_live.reconstructor_settings import ReconstructorSettings
from edi_live.reconstructor_view import ReconstructorView


_BEHIND_CAP = 1 << 20  # events kept unapplied (follow_latent False) before they are applied anyway


class EdiReconstructor(ReconstructorView):
    """Deblurs each APS frame at mid-exposure and advances the latent image event by event.

    `EdiReconstructor(w, h, settings)` or, as a shorthand, `EdiReconstructor(w, h, c=0.25, ...)` with
    ReconstructorSettings' fields as keywords."""

    def __init__(self, width: int, height: int, settings: ReconstructorSettings | None = None, **knobs: Any) -> None:
        if width <= 0 or height <= 0:
            raise ConfigError(f"sensor size must be positive (got {width}x{height})")
        self.settings = settings = resolve_settings(settings, knobs)
        self.width, self.height = int(width), int(height)
        self.c_on, self.c_off, self._fixed = settings.thresholds()
        parts = build_calibration(settings, self.width, self.height)
        self._policy, self._tracker, self._black, self._aps, self._clock = (
            parts.policy, parts.tracker, parts.black, parts.aps, parts.clock)
        self._hot, self._noise, self._unreliable = build_masks(settings, self.width, self.height,
                                                               self._tracker is not None)
        self._flicker = FlickerPixels(self.width, self.height) if settings.mask_flicker_pixels else None
        self._pixel_noise = build_noise(settings, self.width, self.height)  # statistics only (pixel_noise.py)
        self._calib = None if self._tracker is None else FrameCalibration(
            self._policy, self._tracker, self._black, self._clock, self._pixel_noise,
            settled_check_every=settings.settled_check_every)
        # the next exposure's double integral while it runs (not with the noise filter: it drops events later)
        self._ahead = ExposureAhead(self.width, self.height, settings.deblur_ahead and self._noise is None)
        self._mask: np.ndarray | None = self._hot.mask  # events at these pixels are ignored; replaced, not changed
        self._latent = LatentState(self.width, self.height, lone_changes=self.settings.latent_denoise)
        self._carry = edi.ResidualCarry()  # fused mode: what one pair's residual estimate leaves for the next
        self._colour: colour_edi.ColourPlan | None = None  # colour: EDI on the Bayer mosaic, demosaiced for output
        self._pair: contrast.FramePair | None = None  # formed on this frame, judged after its deblur
        self.has_reference = False
        self.follow_latent = True  # see the Reconstructor protocol
        self._behind: list[np.ndarray] = []  # events on_events kept but did not apply (follow_latent False)
        self._behind_n = 0
        self.events_ignored = False  # set when the c policy finds that the events carry no signal
        self._ref_t, self._exposure = 0, (0, 0)
        self._t_last = -(2**63)
        self._pending_events, self._arrival_ns = 0, 0
        self._streamer = False  # a streaming_copy(): its applied events are replayed into the original later
        self.frames = 0
        self.events_applied = 0
        self.last_deblur_ms = 0.0
        self.last_estimate_ms = 0.0

    # ---- state for stats, tools and tests (more in ReconstructorView) ----

    @property
    def latent_log_image(self) -> np.ndarray:
        """A copy of log L(t) at the latest event applied (8-bit scale)."""
        self._catch_up()
        return self._latent.log_lat.copy()

    # ---- the Reconstructor protocol ----

    def mark_gap(self) -> None:
        """A no-op on a streaming_copy(): the caller hands the gap to the original, which owns the pairs."""
        if self._streamer:
            return
        self.settle()
        self._ahead.drop()
        self._carry.clear()
        if self._tracker is not None:
            self._tracker.mark_gap()
        if self._flicker is not None:  # the cycle timing no longer holds: runs under way are forgotten too
            flagged = self._flicker.count
            self._flicker.reset()
            if flagged:
                self._mask = self._combined_mask()

    def streaming_copy(self) -> "EdiReconstructor":
        """Only the latent state (image, display, noise-filter state) is copied: ~30 µs at 346x260, where a deepcopy
        takes ~2 ms. The copy reads the original's hot-pixel mask and reference, which the original replaces
        rather than changes in place; it keeps its c as of now, counts nothing toward c estimation (its events are
        handed to this reconstructor's on_events afterwards anyway) and ignores mark_gap()."""
        twin = copy.copy(self)
        twin._latent = self._latent.streaming_copy()
        twin._hot = copy.copy(self._hot)  # keeps the current mask while the original finds the next one
        twin._noise = self._noise.copy() if self._noise is not None else None
        twin._tracker = twin._flicker = twin._calib = None  # the original finds pairs and flicker in them later
        twin._clock = self._clock.frozen()  # its events reach the original's on_events later
        twin._streamer, twin._pending_events = True, 0  # the events so far count toward the frame being deblurred
        twin._carry = edi.ResidualCarry()  # the carry's scratch belongs to the original's thread
        return twin

    def on_frame(self, frame: Frame, events: np.ndarray, arrival_ns: int = 0,
                 ready: Callable[[Reconstruction], None] | None = None) -> Reconstruction:
        if self._streamer:
            raise NodeError("on_frame() on a streaming_copy(): deblur on the original reconstructor")
        self.settle()  # the previous frame's calibration, if the caller did not settle it
        t_start = time.perf_counter()
        self._colour, img = colour_edi.read_frame(self._colour, frame, self.settings)
        self._latent.lone_changes &= self._colour is None  # a mosaic's neighbours are other colours (edi/lone.py)
        self._behind, self._behind_n = [], 0  # the latent image restarts at this frame's L(f)
        if img.shape != (self.height, self.width):
            raise ConfigError(f"APS frame is {img.shape[1]}x{img.shape[0]} but the reconstructor was set up for "
                              f"{self.width}x{self.height}; check the source resolution")
        off = self.clock_offset_us  # the exposure window in the event clock
        ts, te = int(frame.exposure_start_us) + off, int(frame.exposure_end_us) + off
        f = frame.mid_exposure_us + off
        if self.has_reference and f <= self._ref_t:
            self.mark_gap()  # time went backwards (new recording, loop without offset): start over
        t_all = events["t"]
        n_new = t_all.size - edi.time_index(t_all, self._t_last, "right")
        if self._flicker is not None and (due := self._flicker.due()) is not None:
            self._take_flicker(*due)  # what the events before this frame flagged, not taken yet
        self._observe_flicker(events[t_all.size - n_new:])  # the deblur leaves out newly flagged pixels
        mask = self._mask
        t_batch_end = int(t_all[-1]) if t_all.size else self._t_last
        if self._noise is not None:
            events = self._noise.exposure(events, self._t_last)
        if self._calib is not None:
            t0 = time.perf_counter()
            # the accumulators are used (and written) only when c is estimated; the pair takes them over
            self._pair, self._aps = self._calib.before_deblur(frame, events, img, self._aps, (ts, te, f), mask,
                                                              self._latent.take_counts(), self._t_last,
                                                              self.has_reference)
            self.c_on, self.c_off = self._policy.c
            self.events_ignored = self._policy.events_ignored
            self.last_estimate_ms = (time.perf_counter() - t0) * 1e3
        frame_counts = self._hot.frame_counts if self._hot.enabled else None
        running = self._ahead.take(events, ts, te, f, self._c(), mask, frame_counts)  # the integral so far, if any
        counts_after_f = None if self._fixed else self._latent.acc
        divisor = running.finish(counts_after_f) if running is not None else edi.log_divisor_events(
            events, self.width, self.height, ts, te, f, self.c_on, self.c_off, mask=mask, event_counts=frame_counts,
            counts_after_f=counts_after_f)
        if self.events_ignored:  # still scene: L(f) = B and the latent image stays there
            divisor = (divisor[0][:0], divisor[1][:0], divisor[2][:0] if divisor[2] is not None else None)
        log_prev = self._latent.log_ref
        step = int(self.settings.divisor_median and self._colour is None)  # not on a mosaic (edi/smoothing.py)
        deblurred, display_current = self._latent.set_reference(img, self._aps, divisor, self._c(), step)
        pair, self._pair = self._pair, None
        if self._calib is not None:  # each pixel's noise rate, from the counts of its still intervals (settle)
            self._calib.after_deblur(pair, f - self._ref_t, mask)
        unreliable = self._unreliable if pair is not None and not self.events_ignored else None
        if unreliable is not None and pair is not None:
            # judged on this deblur; the mask holds from here on (the latent image continues from L(f))
            unreliable.update(pair.n_on, pair.n_off, log_prev, self._latent.log_ref, pair.prev.informative,
                              pair.cur.informative, self._c(), busy=frame_counts)
            if unreliable.count:
                self._latent.fall_back_to_aps(unreliable.mask, pair.cur.blurry, deblurred, img, self._aps)
        self.has_reference = True
        self._ref_t = f
        self._exposure = (ts, te)
        self.frames += 1
        self.events_applied += n_new
        n_events = self._pending_events + n_new
        self._pending_events = 0
        self._arrival_ns = arrival_ns or self._arrival_ns
        out = self._reconstruction(deblurred, f, "deblurred", n_events)
        if ready is not None:
            ready(out)  # the frame is complete: what follows only readies the state for the events after it
        if unreliable is not None:  # the mask with this frame's unreliable pixels: the events after it need it
            self._mask = self._combined_mask()
            mask = self._mask if unreliable.count else mask
        t = events["t"]
        # the events after the point the latent image has reached (te with the f -> te jump, else f); with the
        # jump, the divisor pass already added (f, te] to the counts the consistency pairs need
        after = events[edi.time_index(t, te if divisor[2] is not None else f, "right"):]
        self._latent.apply(after, self._c(), mask, count=not self._fixed, move=not self.events_ignored,
                           display=display_current)
        if not display_current:
            self._latent.refresh_display()
        if self._calib is not None:
            self._latent.prepare_counts()  # the next frame's take_counts() finds them zeroed
        if frame_counts is not None:
            self._hot.end_exposure(te - ts)
            self._mask = self._combined_mask()
        self._t_last = max(self._t_last, t_batch_end, f)
        self._ahead.arm(ts, te, self._c(), self._mask, self._hot.frame_counts if self._hot.enabled else None,
                        self._t_last)
        self.last_deblur_ms = (time.perf_counter() - t_start) * 1e3
        return out

    def settle(self) -> None:
        """The latest frame's calibration work that its deblur did not wait for (frame_calibration); on_frame,
        on_events and mark_gap run it first if the caller did not. A new c applies from the next frame on."""
        if self._calib is None or self._streamer or not self._calib.pending:
            return
        self._calib.settle()
        self._ahead.rearm(self._policy.c)  # nothing was fed yet: the next exposure's integral, with the next c

    def on_events(self, events: np.ndarray, arrival_ns: int = 0) -> None:
        self.settle()
        if events.size == 0 or not self.has_reference:
            return  # nothing to advance yet; the first APS frame rebuilds everything
        self._clock.collect(events)
        if not self._streamer:
            self._ahead.feed(events)
        start = 0
        for at, mask, flagged in self._flicker_steps(events):
            self._advance(events[start:at])
            self._take_flicker(mask, flagged)
            start = at
        self._advance(events[start:])
        if arrival_ns:
            self._arrival_ns = arrival_ns

    def _advance(self, events: np.ndarray) -> None:
        """Move the latent image through events (the clock and running integral have seen them; flicker too)."""
        n = int(events.size)
        if n == 0:
            return
        t_end = int(events["t"][-1])
        if self._noise is not None:
            events = self._noise.stream(events)
        self._latent.apply(events, self._c(), self._mask, count=self._counting(),
                           move=self.follow_latent and not self.events_ignored)
        if not (self.follow_latent or self.events_ignored):  # kept; applied if render() needs the latent image
            self._behind.append(events)
            self._behind_n += n
            if self._behind_n > _BEHIND_CAP:
                self._catch_up()  # bounded memory
        self._t_last = max(self._t_last, t_end)
        self._pending_events += n
        self.events_applied += n

    def on_events_frames(self, events: np.ndarray, cuts: Sequence[int],
                         arrivals: Sequence[int]) -> list[Reconstruction]:
        """The frames of on_events(piece, arrival) + render() per piece, with the propagation's arguments set up
        once per batch, not once per frame (the streaming worker's hot path: ~5 µs of a ~25 µs frame)."""
        self._need_reference("on_events_frames()")
        self.settle()
        if not cuts:
            self.on_events(events, 0)
            return []
        self._clock.collect(events)
        if not self._streamer:
            self._ahead.feed(events)
        out, start, steps = [], 0, self._flicker_steps(events)
        for at, mask, flagged in steps + [(int(events.size), None, None)]:  # flags take effect between
            mine = [k for k, c in enumerate(cuts) if start < c <= at]
            piece = events[start:at]
            if not mine:
                self._advance(piece)
            elif self._noise is not None or self.events_ignored:
                out += self._frames_one_by_one(piece, [cuts[k] - start for k in mine], [arrivals[k] for k in mine])
            else:
                out += self._frames(piece, [cuts[k] - start for k in mine], [arrivals[k] for k in mine])
            if flagged is not None:
                self._take_flicker(mask, flagged)
            start = at
        return out

    def _frames(self, events: np.ndarray, cuts: Sequence[int], arrivals: Sequence[int]) -> list[Reconstruction]:
        t = events["t"]

        def frame(k: int, i1: int) -> Reconstruction:
            if arrivals[k]:
                self._arrival_ns = arrivals[k]
            i0 = cuts[k - 1] if k else 0
            rec = self._reconstruction(self._latent_image(), int(t[i1 - 1]), "latent",
                                       self._pending_events + i1 - i0, shown=True)
            self._pending_events = 0
            return rec

        out = self._latent.apply_with_frames(events, cuts, self._c(), self._mask, self._counting(), frame)
        self._pending_events += int(events.size) - cuts[-1]
        self._t_last = max(self._t_last, int(t[-1]))
        self.events_applied += int(events.size)
        return out

    def replay_frames(self, events: np.ndarray, cuts: Sequence[int], arrivals: Sequence[int]) -> None:
        """The state on_events_frames(events, cuts, arrivals) leaves, without rendering its frames: the deblur
        thread's replay of what its streaming copy was given (deblur_handover; a render costs a display copy)."""
        if not cuts or self._noise is not None or self.events_ignored or not self.follow_latent:
            self.on_events_frames(events, cuts, arrivals)  # frame by frame there: its pieces matter
            return
        self.on_events(events, next((a for a in reversed(arrivals) if a), 0))  # what the batched pass does
        self._pending_events = int(events.size) - cuts[-1]

    def render(self) -> Reconstruction:
        self._need_reference("render()")
        n = self._pending_events
        self._pending_events = 0
        self._catch_up()
        return self._reconstruction(self._latent_image(), self._t_last, "latent", n, shown=True)

    def render_from_reference(self, t_us: int, events: np.ndarray) -> Reconstruction:
        self._need_reference("render_from_reference()")
        image = self._latent.from_reference_events(events, self._ref_t, int(t_us), self._c(), self._mask,
                                                   ignored=self.events_ignored)
        return self._reconstruction(image, int(t_us), "latent", int(events.size))

    def reference_log(self) -> tuple[np.ndarray, int]:
        """(log L(f) of the current reference, f): the array is replaced at the next frame, never changed, so
        holding it costs nothing (fused mode keeps the previous one)."""
        self._need_reference("reference_log()")
        return self._latent.log_ref, int(self._ref_t)

    def render_fused(self, previous: tuple[np.ndarray, int] | None, previous_image: np.ndarray | None,
                     current_image: np.ndarray | None, times: Sequence[int], events: np.ndarray) -> list[Reconstruction]:
        """Latent frames at `times` (ascending, f0 < t < f1) from both references (edi.fused_frames: what `events`
        must hold); previous None: forward from the current one, times after f1. Frames carry ref_t_us = f1."""
        self._need_reference("render_fused()")
        informative = None if previous is None else (
            self._aps.to_float(colour_edi.as_mosaic(self._colour, previous_image))[1],
            self._aps.to_float(colour_edi.as_mosaic(self._colour, current_image))[1])
        frames = edi.fused_frames(self.reference_log(), previous, informative, times,
                                  events[:0] if self.events_ignored else events, self._c(), self._mask,
                                  residual=self.settings.fused_residual,
                                  carry=None if self.events_ignored else self._carry)
        return [self._reconstruction(image, t, "latent", n) for image, t, n in frames]

    def fused_events_from(self, f0_us: int, f1_us: int) -> int:
        """The earliest event time render_fused needs for the pair (f0, f1): edi.RESIDUAL_COLD_CONTEXT intervals of
        context for the residual estimate, or a little before f0 when the last pair's pass can be carried on."""
        if not self.settings.fused_residual:
            return int(f0_us) + 1
        if self._carry.warm(f0_us, int(edi.RESIDUAL_SPAN * (f1_us - f0_us)), self._mask):
            return self._carry.snap_us + 1
        return int(f0_us) - edi.RESIDUAL_COLD_CONTEXT * (int(f1_us) - int(f0_us))

    # ---- internals ----

    def _combined_mask(self, flicker: np.ndarray | None = None) -> np.ndarray | None:
        return combined_mask(self._hot, self._unreliable, self._flicker, flicker)

    def _flicker_steps(self, events: np.ndarray) -> list:
        """Where flicker flags found in the events take effect (FlickerPixels.steps); none if not watched."""
        return [] if self._flicker is None or self._streamer else self._flicker.steps(events)

    def _take_flicker(self, mask: np.ndarray | None, flagged: np.ndarray) -> None:
        if mask is not None:  # the flicker mask as of this point of the stream (`steps` may have read further)
            self._mask = self._combined_mask(mask)
        if flagged.size and self.has_reference:
            self._latent.restart_pixels(flagged)

    def _observe_flicker(self, events: np.ndarray) -> None:
        """Pixels flickering in `events` join the mask at once; the latent image restarts there (flicker_pixels)."""
        if self._flicker is not None and not self._streamer and events.size:
            changed, flagged = self._flicker.observe(events)
            self._take_flicker(self._flicker.mask if changed else None, flagged)

    def _c(self) -> tuple[float, float]:
        return self.c_on, self.c_off

    def _counting(self) -> bool:
        return not (self._fixed or self._streamer)

    def _catch_up(self) -> None:
        """Apply the events that on_events only kept (follow_latent False): the latent image is current again."""
        behind, self._behind, self._behind_n = self._behind, [], 0
        for events in behind:
            self._latent.apply(events, self._c(), self._mask, count=False, move=True)

    def _frames_one_by_one(self, events: np.ndarray, cuts: Sequence[int], arrivals: Sequence[int]) -> list:
        out, i0 = [], 0
        for i1, arrival in zip(cuts, arrivals):
            self._advance(events[i0:i1])
            self._arrival_ns = arrival or self._arrival_ns
            out.append(self.render())
            i0 = i1
        self._advance(events[i0:])
        return out

    def _reconstruction(self, image: np.ndarray, t_us: int, kind: str, n_events: int,
                        shown: bool = False) -> Reconstruction:
        """`shown`: `image` is already in output form (see _latent_image)."""
        if self._colour is not None and not shown:
            image = self._colour.output(image)
        return Reconstruction(image=image, t_us=int(t_us),
                              kind=kind, ref_t_us=int(self._ref_t), exposure_start_us=self._exposure[0],
                              exposure_end_us=self._exposure[1], c_on=float(self.c_on), c_off=float(self.c_off),
                              n_events=int(n_events), arrival_ns=int(self._arrival_ns), black_level=self.black_level,
                              aps_gamma=self.aps_gamma)
