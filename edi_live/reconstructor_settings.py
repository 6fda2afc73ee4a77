"""The reconstructor's tuning knobs, one frozen dataclass: thresholds (given, or estimated and how), pixel masks,
the APS black level and the event clock offset. Checked where they are combined (thresholds())."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import edi_live.contrast as contrast
from edi_live.c_policy import C_RANGE
from edi_live.colour import DEFAULT_DEMOSAIC, DEMOSAIC_METHODS
from edi_live.datatypes import COLOR_FILTERS, ColorFilter
from edi_live.errors import ConfigError

if TYPE_CHECKING:
    from edi_live.pixel_noise import NoiseRates


@dataclass(frozen=True)
class ReconstructorSettings:
    """Thresholds and tuning of the reconstructor. c (or c_on and c_off) fixes the thresholds; otherwise they are
    estimated (`estimator`, starting at c_init) and cached by the c policy."""

    c: float | None = None
    c_on: float | None = None
    c_off: float | None = None
    estimator: str = contrast.DEFAULT_ESTIMATOR
    estimator_options: dict = field(default_factory=dict)
    separate_thresholds: bool = True  # estimate c_on and c_off apart (one c when the data cannot separate them)
    c_init: float = 0.2
    c_start: tuple[float, float] | None = None  # (c_on, c_off) to start estimating from, e.g. a saved calibration
    reestimate_every: int = 0  # frames; 0 = only when the fit test fails
    history_pairs: int = 2  # consecutive-frame pairs the estimator sees
    fit_patience: int = 2
    fit_strong: float = 3.0
    c_history: int = 3  # accepted estimates whose median is c
    joint_pairs: int = 0  # > 0: c from the last K pairs pooled, odd pairs set aside (edi_live.contrast.joint)
    # once the calibration has settled, c's fit test on every this-many-th APS frame (edi_live.calibration_schedule);
    # 1: every frame. Back to every frame when anything changes
    settled_check_every: int = 4
    sample_pixels: int = 4000  # pixels on which c is estimated
    mask_hot_pixels: bool = True
    hot_min_rate_hz: float = 300.0
    hot_rel_factor: float = 10.0
    hot_decay: float = 0.8
    saturation: float | None = None  # APS value at or above which a pixel is clipped (default: full scale)
    # APS value of no light (8-bit scale), taken off B so that frames are linear. None (the default): estimated
    # from the stream (black_level_policy; needs c estimation and aps_gamma 1), 0 DN until dark pixels support a
    # value above 3 DN, as on DV's 8-bit frames that reach 0 DN (docs/calibration.md)
    black_level: float | None = None
    aps_gamma: float = 1.0  # APS response: value = black + 255 (I/255)^(1/gamma); undone before the deblur
    # events arrive this much later than the APS exposure they belong to (event time = APS time + offset), µs;
    # the frame's exposure window and reference time are moved into the event clock by it
    # None: estimated from the stream (clock_offset_policy; needs c estimation, else 0)
    clock_offset_us: int | None = None
    # starting values of an estimated black level and clock offset, e.g. a saved calibration's: in use from the
    # first frame, replaced when the stream's own estimate differs (used as given where nothing is estimated)
    black_level_start: float | None = None
    clock_offset_start_us: int | None = None
    denoise_us: int = 0  # background-activity filter window; 0 = off
    fused_residual: bool = True  # fused mode: add the sub-threshold residual estimate (+1.4 dB; docs/modes.md)
    # grey sensors: the deblurred frame and the latent image at te from the 3x3 median of log D, not each pixel's
    # own (edi.smoothing: ~2 dB at mid-exposure on the simulators); False: plain per-pixel EDI
    divisor_median: bool = True
    # grey sensors, causal latent frames: a pixel whose change since te no two neighbours share shows its value at te
    # (edi/lone.py: no lone dots from one pixel's extra or missing events; one pass over each frame)
    latent_denoise: bool = False
    deblur_ahead: bool = True  # accumulate the next exposure's double integral while it runs (exposure_ahead.py)
    mask_unreliable_pixels: bool = True  # ignore events that contradict the APS frames (needs c estimation)
    mask_flicker_pixels: bool = True  # ignore the events of pixels that flicker at a mains period (flicker_pixels)
    # per-pixel noise rates (pixel_noise.py): estimated from the frame pairs while c is estimated; a given
    # noise_rate_hz (ON + OFF, every pixel) replaces the estimate; noise_start: a saved estimate to start from
    noise_stats: bool = True
    noise_rate_hz: float | None = None
    noise_start: NoiseRates | None = field(default=None, compare=False, repr=False)
    # colour sensor (edi_live.colour_edi): the source's Bayer pattern (None: grey, unless a frame says otherwise);
    # EDI runs on the mosaic, output is demosaiced BGR (`demosaic`: colour.DEMOSAIC_METHODS), or grey with `gray`
    color_filter: ColorFilter | None = None
    gray: bool = False
    demosaic: str = DEFAULT_DEMOSAIC

    def __post_init__(self) -> None:
        if self.color_filter is not None and self.color_filter not in COLOR_FILTERS:
            raise ConfigError(f"unknown Bayer pattern {self.color_filter!r} (known: {', '.join(COLOR_FILTERS)})")
        if self.demosaic not in DEMOSAIC_METHODS:
            raise ConfigError(f"unknown demosaicing method {self.demosaic!r} (known: {', '.join(DEMOSAIC_METHODS)})")
        if not (isinstance(self.settled_check_every, int) and 1 <= self.settled_check_every <= 100):
            raise ConfigError(f"settled_check_every must be a whole number of frames in [1, 100] "
                              f"(got {self.settled_check_every!r})")

    def thresholds(self) -> tuple[float, float, bool]:
        """(c_on, c_off, fixed), checked."""
        c, c_on, c_off = _check_c("c", self.c), _check_c("c_on", self.c_on), _check_c("c_off", self.c_off)
        if (c_on is None) != (c_off is None) and c is None:
            raise ConfigError("give both c_on and c_off (or a single c)")
        fixed = c is not None or c_on is not None
        start = (None, None) if self.c_start is None else (_check_c("c_start", self.c_start[0]),
                                                            _check_c("c_start", self.c_start[1]))
        on = c_on if c_on is not None else (c if c is not None else start[0] or _check_c("c_init", self.c_init))
        off = c_off if c_off is not None else (c if c is not None else start[1] or on)
        return on, off, fixed


def _check_c(name: str, value: float | None) -> float | None:
    if value is None:
        return None
    v = float(value)
    if not (math.isfinite(v) and C_RANGE[0] <= v <= C_RANGE[1]):
        raise ConfigError(f"{name} must be a contrast threshold in [{C_RANGE[0]}, {C_RANGE[1]}] (got {value!r})")
    return v
