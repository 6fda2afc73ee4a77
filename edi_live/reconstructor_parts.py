"""The parts an EdiReconstructor owns, built from its one ReconstructorSettings: the c estimator and its policy and
frame-pair tracker, the APS response with its black-level and clock-offset policies, and the pixel masks.

Building them here keeps the reconstructor about what happens per frame and per event; every setting that can be
wrong is checked here and refused as a ConfigError (one line for the person at the terminal).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.black_level_policy import BlackLevelPolicy
from edi_live.c_policy import ContrastPolicy, PolicySettings
from edi_live.clock_offset_policy import ClockOffsetPolicy
from edi_live.contrast_tracking import ContrastTracker
from edi_live.errors import ConfigError
from edi_live.pixel_masks import HotPixels, NoiseFilter, UnreliablePixels
from edi_live.pixel_noise import PixelNoise
from edi_live.reconstructor_settings import ReconstructorSettings


def resolve_settings(settings: ReconstructorSettings | None, knobs: dict[str, Any]) -> ReconstructorSettings:
    """`settings` (or the defaults) with `knobs` (ReconstructorSettings' fields as keywords) applied and checked."""
    try:
        settings = dataclasses.replace(settings or ReconstructorSettings(), **knobs)
    except TypeError as exc:
        raise ConfigError(f"unknown reconstructor setting ({exc})") from None
    if settings.reestimate_every < 0:
        raise ConfigError(f"reestimate_every must be >= 0 (got {settings.reestimate_every})")
    return settings


def make_estimator(settings: ReconstructorSettings, c_on: float, c_off: float,
                   fixed: bool) -> contrast.ContrastEstimator:
    """The c estimator the settings ask for (a fixed one when c is given)."""
    if fixed:
        return contrast.FixedContrast(c_on, c_off)
    try:
        options = dict(settings.estimator_options)
        if settings.estimator == "consistency":
            options.setdefault("separate", settings.separate_thresholds)
        elif settings.estimator == "energy":  # its TV/Sobel terms per same-channel sub-image in colour
            options.setdefault("mosaic", settings.color_filter is not None)
        return contrast.make_estimator(settings.estimator, **options)
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc)) from None


@dataclass
class Calibration:
    """What decides the camera values: c (policy, and the tracker of frame pairs unless c is fixed), the APS
    response with its black-level policy, and the event clock offset policy."""

    policy: ContrastPolicy
    tracker: ContrastTracker | None
    black: BlackLevelPolicy
    aps: edi.ApsResponse
    clock: ClockOffsetPolicy


def build_calibration(settings: ReconstructorSettings, width: int, height: int) -> Calibration:
    c_on, c_off, fixed = settings.thresholds()
    estimator = make_estimator(settings, c_on, c_off, fixed)
    try:
        # estimated only when c is too, and not under a given response (the fit assumes a linear APS)
        estimated = settings.black_level is None and not fixed and settings.aps_gamma == 1.0
        black = BlackLevelPolicy(None if estimated else float(_first(settings.black_level, settings.black_level_start)),
                                 start=settings.black_level_start)
        aps = edi.ApsResponse(settings.saturation, black.value, float(settings.aps_gamma))
    except (TypeError, ValueError) as exc:
        raise ConfigError(str(exc)) from None
    clock = ClockOffsetPolicy(None if settings.clock_offset_us is None and not fixed
                              else _first(settings.clock_offset_us, settings.clock_offset_start_us), width, height,
                              start=settings.clock_offset_start_us)
    policy = ContrastPolicy(estimator, c_on, c_off, PolicySettings(
        reestimate_every=int(settings.reestimate_every), startup_estimates=settings.history_pairs,
        fit_patience=int(settings.fit_patience), fit_strong=float(settings.fit_strong),
        c_history=int(settings.c_history), joint_pairs=int(settings.joint_pairs)))
    tracker = None if fixed else ContrastTracker(width, height, policy,
                                                 history_pairs=max(settings.history_pairs, settings.joint_pairs),
                                                 sample_pixels=settings.sample_pixels)
    return Calibration(policy, tracker, black, aps, clock)


def build_masks(settings: ReconstructorSettings, width: int, height: int,
                estimating: bool) -> tuple[HotPixels, NoiseFilter | None, UnreliablePixels | None]:
    """(hot pixels, the background-activity filter or None, unreliable pixels or None). Unreliable pixels are found
    only while c is estimated (`estimating`): they are judged on the frame pairs the tracker forms."""
    hot = HotPixels(width, height, enabled=settings.mask_hot_pixels, min_rate_hz=settings.hot_min_rate_hz,
                    rel_factor=settings.hot_rel_factor, decay=settings.hot_decay)
    noise = NoiseFilter(width, height, settings.denoise_us) if settings.denoise_us > 0 else None
    unreliable = (UnreliablePixels(width, height, grow_px=2)
                  if settings.mask_unreliable_pixels and estimating else None)
    return hot, noise, unreliable


def build_noise(settings: ReconstructorSettings, width: int, height: int) -> PixelNoise:
    """The per-pixel noise statistics: estimated, fixed (noise_rate_hz) or off (noise_stats False)."""
    rate = settings.noise_rate_hz
    if rate is not None and not (isinstance(rate, (int, float)) and math.isfinite(rate) and 0 <= rate <= 1e6):
        raise ConfigError(f"noise_rate_hz must be a rate in Hz per pixel in [0, 1e6] (got {rate!r})")
    return PixelNoise(width, height, enabled=settings.noise_stats, fixed_hz=None if rate is None else float(rate),
                      start=settings.noise_start)


def _first(given, start):
    """A given value, else a starting value, else 0."""
    return given if given is not None else (start if start is not None else 0)
