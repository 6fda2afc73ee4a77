"""The latent image between APS frames: log L(f) of the current reference (each pixel's own, and the one the
deblurred frame showed: edi.smoothing's), log L(t) advanced event by event with its uint8 display kept up to date,
and the ON/OFF counts applied since f (which the c estimator needs).

Owns only arrays and the operations on them (edi_live.edi does the math). Emitting a latent frame costs
O(new events) plus one copy of the display.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

import edi_live.edi as edi


class LatentState:
    def __init__(self, width: int, height: int, *, lone_changes: bool = False) -> None:
        """`lone_changes`: shown_image() hides lone changes since the latent image started (edi.lone)."""
        self.width, self.height = width, height
        self.lone_changes = lone_changes
        self._lone: edi.LoneChanges | None = None  # where each pixel started, from the first reference on
        # replaced per frame; changed in place only by the fall-back to the APS, before anything else reads the frame's
        self.log_ref = np.zeros((height, width), np.float32)
        self.log_shown = self.log_ref  # the L(f) the deblurred frame showed (edi.smoothing), or log_ref itself
        self.log_lat = np.zeros((height, width), np.float32)
        self.display = np.zeros((height, width), np.uint8)
        npix = width * height
        self.acc = (np.zeros(npix, np.int64), np.zeros(npix, np.int64))  # ON/OFF applied since f
        self._spare: tuple[np.ndarray, np.ndarray] | None = None  # zeroed counts for the next take_counts()
        self._median_scratch: np.ndarray | None = None  # the smoothed divisor's work grid (kept zeroed)

    def streaming_copy(self) -> "LatentState":
        """Own image, display and lone-change state; the references (log_ref, log_shown) and the counts are shared
        (the copy reads the one and never writes the other; once the original's frame pair has taken the counts over,
        they are the pair's, which the deblur thread changes: a copy's counts mean nothing then)."""
        twin = LatentState.__new__(LatentState)
        twin.width, twin.height = self.width, self.height
        twin.log_ref, twin.acc, twin._spare, twin._median_scratch = self.log_ref, self.acc, None, None
        twin.log_shown = self.log_shown
        twin.log_lat, twin.display = self.log_lat.copy(), self.display.copy()
        # its own start: the original's restarts change the original's in place, while the copy streams on
        twin.lone_changes, twin._lone = self.lone_changes, None if self._lone is None else self._lone.copy()
        return twin

    def take_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """The counts so far, handed over (the caller may change them); counting restarts from zero, in the arrays
        prepare_counts() zeroed if it ran since the last take (a copy and a fill less before the deblurred frame)."""
        taken, spare, self._spare = self.acc, self._spare, None
        self.acc = spare if spare is not None else (np.zeros_like(taken[0]), np.zeros_like(taken[1]))
        return taken

    def prepare_counts(self) -> None:
        """Zeroed arrays for the next take_counts(), filled now (after the frame has left) rather than then."""
        if self._spare is None:
            npix = self.width * self.height
            self._spare = (np.empty(npix, np.int64), np.empty(npix, np.int64))
            for a in self._spare:
                a.fill(0)

    def apply(self, events: np.ndarray, c: tuple[float, float], mask: np.ndarray | None, *, count: bool,
              move: bool, display: bool = True) -> None:
        """Advance log L(t) over `events` (unless `move` is False: then only count them, if `count`)."""
        if not move:
            if count:
                edi.add_counts(events, self.width, self.height, *self.acc, mask=mask)
            return
        edi.propagate_log(self.log_lat, events, c[0], c[1], mask=mask, display=self.display if display else None,
                          counts=self.acc if count else None)
        if self._lone is not None:
            self._lone.touched(events["x"], events["y"])

    def apply_with_frames(self, events: np.ndarray, cuts: Sequence[int], c: tuple[float, float],
                          mask: np.ndarray | None, count: bool, frame: Callable[[int, int], object]) -> list:
        """apply(events) and, after the first cuts[k] events, `frame(k, i1)` (which copies the display)."""
        prop = edi.Propagator(self.log_lat, self.display, c[0], c[1], mask, self.acc if count else None)
        x, y, p = events["x"], events["y"], events["p"]
        out = []
        i0 = 0
        lone = self._lone
        for k, i1 in enumerate(cuts):
            prop.apply(x[i0:i1], y[i0:i1], p[i0:i1])
            if lone is not None:
                lone.touched(x[i0:i1], y[i0:i1])
            out.append(frame(k, i1))
            i0 = i1
        if i0 < events.size:
            prop.apply(x[i0:], y[i0:], p[i0:])
            if lone is not None:
                lone.touched(x[i0:], y[i0:])
        return out

    def set_reference(self, image: np.ndarray, aps: edi.ApsResponse,
                      divisor: tuple[np.ndarray, np.ndarray, np.ndarray | None],
                      c: tuple[float, float], median_step: int = 0) -> tuple[np.ndarray, bool]:
        """Deblur: log L(f) from B and the divisor; the latent image restarts there, moved on to te when the
        divisor carries the f -> te exponent. Returns (L(f) as uint8, whether the display is current: the fused
        pass of a uint8 frame also renders it; otherwise the caller refreshes it).

        `median_step` > 0: the uint8 L(f) (and `log_shown`, its log image) and the latent image at te come from the
        3x3 median of the divisor over neighbouring pixels (edi.smoothed_divisor; the reconstructor passes 1, and
        never smooths a Bayer mosaic); log_ref, which the per-pixel tests and nearest and fused modes read, keeps each
        pixel's own."""
        pixels, log_d, delta_end = divisor
        shown = None
        if median_step and pixels.size:
            if self._median_scratch is None:
                self._median_scratch = edi.new_median_scratch(self.width, self.height)
            shown = edi.smoothed_divisor(divisor, self.width, self.height, median_step, scratch=self._median_scratch)
        if image.dtype == np.uint8 and delta_end is not None and (edi.have_numba() or shown is not None):
            deblurred = np.empty((self.height, self.width), np.uint8)
            self.log_ref = np.empty((self.height, self.width), np.float32)
            self.log_shown = self.log_ref if shown is None else np.empty((self.height, self.width), np.float32)
            sat = 255.0 if aps.saturation is None else float(aps.saturation)
            edi.finish_frame_u8(image, sat, divisor, self.log_ref, deblurred, self.log_lat, self.display,
                                black_level=aps.black_level, gamma=aps.gamma, shown=shown, log_shown=self.log_shown)
            self._new_start(self.display)
            return deblurred, True
        b, informative = aps.to_float(image)
        shown_d, jump = (None, delta_end) if shown is None else shown
        self.log_ref, self.log_shown, lat = edi.reference_logs(b, informative, pixels, log_d, shown_d, jump)
        np.copyto(self.log_lat, lat)
        # the display is refreshed by the caller after later events: the start is shown as the numpy path renders it
        self._new_start(edi.to_uint8(self.log_lat))
        return edi.to_uint8(self.log_shown), False

    def _new_start(self, display: np.ndarray) -> None:
        if self.lone_changes:
            if self._lone is None:
                self._lone = edi.LoneChanges(self.width, self.height)
            self._lone.restart(self.log_lat, display)

    def shown_image(self) -> np.ndarray:
        """The latent display as output, a new (H, W) uint8 array: a copy, or with lone_changes (from the first
        reference on) a pixel whose change since it started no two neighbours share shows its start (edi.lone)."""
        if not self.lone_changes or self._lone is None:
            return self.display.copy()
        return self._lone.image(self.log_lat, self.display)

    def fall_back_to_aps(self, pixels: np.ndarray, b: np.ndarray, deblurred: np.ndarray,
                         image: np.ndarray | None = None, aps: edi.ApsResponse | None = None) -> None:
        """At `pixels` ((H, W) bool), undo the events: L(f) = B (`b`: the frame's ApsResponse.to_float) and the
        latent image restarts there (the reference of this frame only; it is this state's own array until the
        next frame). Given the frame `image` and `aps` it came with, a uint8 frame takes its values from the
        tables of its 256 values (edi.u8_tables: the same formulas; one compiled pass, ~10 µs against ~35)."""
        if image is not None and aps is not None and image.dtype == np.uint8 and edi.have_numba():
            edi.fall_back_u8(pixels, image, aps.black_level, aps.gamma, self.log_ref, self.log_lat, self.display,
                             deblurred)
        else:
            idx = np.flatnonzero(pixels)
            log_b = np.clip(np.log(np.maximum(b.reshape(-1)[idx], edi.DARK_FLOOR)), edi.LOG_MIN, edi.LOG_MAX)
            self.log_ref.reshape(-1)[idx] = log_b
            self.log_lat.reshape(-1)[idx] = log_b
            shown = edi.to_uint8(log_b.astype(np.float32))
            self.display.reshape(-1)[idx] = shown
            deblurred.reshape(-1)[idx] = shown
        if self.log_shown is not self.log_ref:  # the L(f) shown is B there too
            np.copyto(self.log_shown, self.log_ref, where=pixels.reshape(self.log_ref.shape))
        if self._lone is not None:  # the latent image starts there again
            self._lone.restart_at(np.flatnonzero(pixels), self.log_lat, self.display)

    def restart_pixels(self, pixels: np.ndarray) -> None:
        """At `pixels` (flat indices), the latent image goes back to the L(f) the deblurred frame showed."""
        ref = self.log_shown.reshape(-1)[pixels]
        self.log_lat.reshape(-1)[pixels] = ref
        self.display.reshape(-1)[pixels] = edi.to_uint8(ref)
        if self._lone is not None:
            self._lone.restart_at(pixels, self.log_lat, self.display)

    def refresh_display(self) -> None:
        np.copyto(self.display, edi.to_uint8(self.log_lat))
        if self._lone is not None:
            self._lone.changed_everywhere()

    def from_reference(self, delta: np.ndarray | float) -> np.ndarray:
        """uint8 image of L(f) * exp(delta), without touching the latent state."""
        return edi.to_uint8(np.clip(self.log_ref + delta, edi.LOG_MIN, edi.LOG_MAX))

    def from_reference_events(self, events: np.ndarray, f: int, t_us: int, c: tuple[float, float],
                              mask: np.ndarray | None, *, ignored: bool = False) -> np.ndarray:
        """uint8 image at t_us from L(f) and the events between f and t_us (either side of f; none if `ignored`),
        without touching the latent state."""
        if ignored:
            return self.from_reference(0.0)
        if t_us >= f:
            return self.from_reference(edi.event_delta(events, self.width, self.height, c[0], c[1], t0=f + 1,
                                                       t1=t_us, mask=mask))
        return self.from_reference(-edi.event_delta(events, self.width, self.height, c[0], c[1], t0=t_us + 1,
                                                    t1=f, mask=mask))
