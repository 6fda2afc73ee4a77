"""Read-only views of an EdiReconstructor's state for stats, tools and tests: the camera values in force, the c
policy's counters, the pixel masks' counts and the noise statistics, and the stats() map of them all.

ReconstructorView is EdiReconstructor's base class; the attributes it reads are set by EdiReconstructor.__init__.
Reading them from another thread (the stats map) is safe: each read is one plain value. Except `pairs`, which
completes a pending level table first: call it from the thread that runs the reconstructor.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.black_level_policy import BlackLevelPolicy
from edi_live.c_policy import ContrastPolicy
from edi_live.clock_offset_policy import ClockOffsetPolicy
from edi_live.contrast_tracking import ContrastTracker
from edi_live.exposure_ahead import ExposureAhead
from edi_live.flicker_pixels import FlickerPixels
from edi_live.frame_calibration import FrameCalibration
from edi_live.latent_state import LatentState
from edi_live.pixel_masks import HotPixels, UnreliablePixels
from edi_live.errors import NodeError
from edi_live.pixel_noise import NoiseRates, PixelNoise


class ReconstructorView:
    """The read-only properties of an EdiReconstructor."""

    _aps: edi.ApsResponse
    _clock: ClockOffsetPolicy
    _policy: ContrastPolicy
    _tracker: ContrastTracker | None
    _hot: HotPixels
    _unreliable: UnreliablePixels | None
    _flicker: FlickerPixels | None
    _pixel_noise: PixelNoise
    _latent: LatentState
    _colour: Any  # colour_edi.ColourPlan, or None for a grey sensor
    _black: BlackLevelPolicy
    _ahead: ExposureAhead
    _calib: FrameCalibration | None
    _fixed: bool
    c_on: float
    c_off: float
    frames: int
    events_ignored: bool
    events_applied: int
    has_reference: bool
    last_deblur_ms: float
    last_estimate_ms: float

    @property
    def black_level(self) -> float:  # APS black level (8-bit DN) taken off the frames
        return self._aps.black_level

    @property
    def clock_offset_us(self) -> int:  # events late vs the APS (the worker's windows); may move between frames
        return self._clock.value

    @property
    def aps_gamma(self) -> float:  # APS response exponent undone before the deblur
        return self._aps.gamma

    @property
    def reestimations(self) -> int:
        return self._policy.reestimations

    @property
    def ill_conditioned(self) -> int:
        return self._policy.ill_conditioned

    @property
    def last_fit(self) -> dict:
        return self._policy.last_fit

    @property
    def estimator(self) -> contrast.ContrastEstimator:
        return self._policy.estimator

    @property
    def pairs(self) -> list[contrast.FramePair]:
        """The consecutive-frame pairs the c estimator currently sees whose two frames have their level tables
        (newest last; empty with a fixed c), the latest frame's built even if settle() has not run yet. Once the
        calibration has settled, a frame's table is built only where a fit test or the black level reads it
        (calibration_schedule), so fewer pairs qualify: `settled_check_every=1` keeps every one."""
        if self._tracker is None:
            return []
        self._tracker.complete()
        return [p for p in self._tracker.pairs if p.has_tables]

    @property
    def hot_pixels(self) -> int:
        return self._hot.count

    @property
    def unreliable_pixels(self) -> int:
        """Pixels whose events currently contradict the APS frames (ignored like hot pixels)."""
        return 0 if self._unreliable is None else self._unreliable.count

    @property
    def flicker_pixels(self) -> int:
        """Pixels lit by a flickering (mains) lamp now (their events are ignored like hot pixels')."""
        return 0 if self._flicker is None else self._flicker.count

    def noise_rates(self) -> NoiseRates | None:
        """Per-pixel ON/OFF noise rates observed so far (None when off or given): .estimate(), or save them."""
        return self._pixel_noise.rates()

    @property
    def applied_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the ON/OFF counts per pixel (flat) applied since the reference time f."""
        return self._latent.acc[0].copy(), self._latent.acc[1].copy()

    @property
    def hot_pixel_mask(self) -> np.ndarray:
        return self._hot.snapshot()

    def _need_reference(self, what: str) -> None:
        if not self.has_reference:
            raise NodeError(f"{what} called before the first APS frame was deblurred (check has_reference first)")

    def _latent_image(self) -> np.ndarray:
        """The latent display as output: LatentState.shown_image (grey), or its demosaic (a new array: no copy needed
        first)."""
        if self._colour is None:
            return self._latent.shown_image()
        return self._colour.output(self._latent.display)

    def stats(self, current: bool = False) -> dict:
        return {
            "c_on": self.c_on, "c_off": self.c_off, "c_fixed": self._fixed, "black_level": self.black_level,
            "black_level_estimated": self._black.estimated, "clock_offset_estimated": self._clock.estimated,
            "black_level_from_calibration": self._black.from_calibration,
            "clock_offset_from_calibration": self._clock.from_calibration,
            "clock_offset_physical_us": self._clock.physical_us,
            "estimator": self.estimator.name, "reestimations": self.reestimations,
            "ill_conditioned": self.ill_conditioned, "hot_pixels": self.hot_pixels,
            "unreliable_pixels": self.unreliable_pixels,
            "flicker_pixels": self.flicker_pixels, "frames": self.frames, **self._pixel_noise.summary(current),
            "events_ignored": self.events_ignored, "deblurs_ahead": self._ahead.used,
            "events_applied": self.events_applied, "has_reference": self.has_reference,
            "last_deblur_ms": round(self.last_deblur_ms, 3), "last_estimate_ms": round(self.last_estimate_ms, 3),
            "last_settle_ms": round(self._calib.last_settle_ms, 3) if self._calib is not None else 0.0,
            # colour only (a grey reconstructor's map is unchanged): the pattern EDI runs on, also when the source
            # named none and its BGR frames started colour at the first frame
            **({"bayer_pattern": self._colour.pattern} if self._colour is not None else {}),
        }
