"""The Reconstructor protocol: everything the worker and the node ask of the EDI core (edi_live.reconstructor
implements it; tests use small stand-ins). Runs on the worker thread; not thread-safe.

Time contract (µs, sensor clock): `on_frame(frame, events)` gets every event from frame.exposure_start_us up to
the caller's "now" (some of them may already have been given to `on_events`); `on_events` gets later events in
time order. Events before the first APS frame are ignored (there is no reference yet).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol, Sequence, runtime_checkable

import numpy as np

from edi_live.datatypes import Frame, Reconstruction

if TYPE_CHECKING:
    from edi_live.pixel_noise import NoiseRates


@runtime_checkable
class Reconstructor(Protocol):
    has_reference: bool  # an APS frame was deblurred: latent frames can be rendered
    c_on: float
    c_off: float
    black_level: float  # APS black level (8-bit DN) taken off the frames
    clock_offset_us: int  # events arrive this much later than the APS exposure they belong to
    aps_gamma: float  # APS response exponent undone before the deblur
    # False (fused mode, set by the worker): on_events keeps the events and applies them only when render() needs
    # the latent image; the frames come from render_fused, so no causal image is advanced beside them
    follow_latent: bool

    @property
    def reestimations(self) -> int: ...

    @property
    def hot_pixels(self) -> int: ...

    @property
    def unreliable_pixels(self) -> int:
        """Pixels whose events are ignored because they contradict the APS frames."""
        ...

    def on_frame(self, frame: Frame, events: np.ndarray, arrival_ns: int = 0,
                 ready: Callable[[Reconstruction], None] | None = None) -> Reconstruction:
        """Deblur `frame` (L(f) at mid-exposure, kind "deblurred"); it becomes the reference. `ready`, if given, is
        called (on this thread) with the frame it returns as soon as the frame is complete, possibly before on_frame
        has finished its state: the caller may send it then, but must not touch the reconstructor until on_frame
        returns."""
        ...

    def settle(self) -> None:
        """The per-frame work that on_frame left for after its frame was sent (the c decision and other
        calibration); what it decides applies from the next on_frame. on_frame, on_events and mark_gap run it first
        if it is still pending, so a caller that never calls it gets the same frames."""
        ...

    def on_events(self, events: np.ndarray, arrival_ns: int = 0) -> None:
        """Advance the latent image over later events."""
        ...

    def on_events_frames(self, events: np.ndarray, cuts: Sequence[int],
                         arrivals: Sequence[int]) -> list[Reconstruction]:
        """on_events(events), rendering a latent frame after the first cuts[k] events, stamped arrivals[k]."""
        ...

    def replay_frames(self, events: np.ndarray, cuts: Sequence[int], arrivals: Sequence[int]) -> None:
        """The state on_events_frames(events, cuts, arrivals) leaves; its frames need not be rendered (the deblur
        thread replays what a streaming copy already sent)."""
        ...

    def render(self) -> Reconstruction:
        """The current latent image (kind "latent")."""
        ...

    def render_from_reference(self, t_us: int, events: np.ndarray) -> Reconstruction:
        """The latent image at t from the reference, using the events between t and f (t may be before f)."""
        ...

    def reference_log(self) -> tuple[np.ndarray, int]:
        """(log L(f) of the current reference, f): kept by fused mode for the next pair."""
        ...

    def fused_events_from(self, f0_us: int, f1_us: int) -> int:
        """The earliest event time render_fused needs for the pair of references at f0 and f1."""
        ...

    def render_fused(self, previous: tuple[np.ndarray, int] | None, previous_image: np.ndarray | None,
                     current_image: np.ndarray | None, times: Sequence[int], events: np.ndarray) -> list[Reconstruction]:
        """Latent frames at `times` between the previous reference and the current one, from both (previous None:
        forward from the current reference, at times after it)."""
        ...

    def mark_gap(self) -> None:
        """Data were lost upstream: do not relate the next frame to the previous one."""
        ...

    def streaming_copy(self) -> "Reconstructor":
        """A copy that streams latent frames from the current reference while this one deblurs the next frame on
        another thread; its events are replayed into this one afterwards."""
        ...

    def stats(self, current: bool = False) -> dict[str, Any]:
        """Counters and camera values; `current`: the run has ended, so figures that are otherwise refreshed only
        every few seconds (the noise summary) are brought up to date."""
        ...

    def noise_rates(self) -> "NoiseRates | None":
        """The per-pixel noise rates to save with a calibration; None when they are not estimated."""
        ...
