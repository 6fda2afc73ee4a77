"""EDI on a colour (Bayer) sensor: what the reconstructor does differently for a colour source, in one place.

EDI runs on the raw mosaic at full event resolution: each pixel's events change the log intensity of its own
channel, so the per-pixel math (level tables, log D, deblur, propagation) is the grey path unchanged. What is
spatial had to be checked (docs/colour.md): the consistency c estimator is per pixel (no change); the energy
estimator's TV and Sobel terms run on the four same-channel sub-images; the hot-pixel rule compares a pixel's rate
with the mean of all active pixels (no neighbours); the unreliable-pixel growth and the background-activity
filter work in scene geometry, which the mosaic keeps.

This module owns:
- `ColourPlan`: the pattern in force, how frames enter (`input_mosaic`: a raw mosaic as is, a BGR frame
  re-mosaiced with the pattern) and how the uint8 mosaic leaves (`output`: demosaiced BGR, or grey with `gray`);
- `resolve_pattern`: which pattern a frame is read with (never grey for a colour frame);
- `channel_contrast`: c estimated per Bayer channel and whether it beats one shared c (a z test).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from edi_live.colour import DEFAULT_DEMOSAIC, channel_map, check_pattern, demosaic, mosaic, mosaic_to_gray
from edi_live.contrast.consistency import ConsistencyContrast
from edi_live.contrast.frames import FramePair
from edi_live.datatypes import ColorFilter, Frame
from edi_live.reconstructor_settings import ReconstructorSettings

DAVIS346_COLOR_FILTER: ColorFilter = "RGGB"  # assumed for BGR input whose source names no pattern
CHANNEL_NAMES = ("B", "G", "R")


def resolve_pattern(configured: ColorFilter | None, frame: Frame) -> ColorFilter | None:
    """The pattern to read `frame` with: the source's (configured) one, else the frame's own, else for a BGR
    frame the DAVIS346 colour default; None only for a grey frame from a grey source."""
    if configured is not None:
        return check_pattern(configured)
    if frame.color_filter is not None:
        return check_pattern(frame.color_filter)
    if frame.image.ndim == 3:
        return DAVIS346_COLOR_FILTER
    return None


@dataclass(frozen=True)
class ColourPlan:
    """How a colour reconstructor reads frames and writes images. `gray`: output grey (h, w) images (OpenCV's
    Bayer -> grey, BT.601 luma, in one pass), e.g. for a grey-only consumer."""

    pattern: ColorFilter
    gray: bool = False
    method: str = DEFAULT_DEMOSAIC

    def input_mosaic(self, image: np.ndarray) -> np.ndarray:
        """The 2-D mosaic EDI runs on: a raw mosaic as it is; a demosaiced BGR frame re-mosaiced with the pattern
        (each pixel keeps the value of the channel its events belong to)."""
        return mosaic(image, self.pattern) if image.ndim == 3 else image

    def output(self, mosaic_u8: np.ndarray) -> np.ndarray:
        """(h, w, 3) uint8 BGR of the reconstructed uint8 mosaic, or (h, w) grey with `gray`."""
        if self.gray:
            return mosaic_to_gray(mosaic_u8, self.pattern)
        return demosaic(mosaic_u8, self.pattern, self.method)


def aps_as_output(frame: Frame, configured: ColorFilter | None, gray: bool) -> np.ndarray:
    """A colour source's APS frame as the node shows it: demosaiced to BGR, or grey with `gray`."""
    plan = ColourPlan(resolve_pattern(configured, frame), gray)  # type: ignore[arg-type]  # never None here
    return plan.output(plan.input_mosaic(frame.image))


def read_frame(plan: ColourPlan | None, frame: Frame, settings: ReconstructorSettings) \
        -> tuple[ColourPlan | None, np.ndarray]:
    """(the plan in force once `frame` is seen, the 2-D image EDI runs on). A grey source's first colour frame
    starts a plan for the frame's pattern, so that a colour frame is never silently read as grey."""
    if plan is None:
        pattern = resolve_pattern(settings.color_filter, frame)
        if pattern is not None:
            plan = ColourPlan(pattern, settings.gray, settings.demosaic)
    return plan, (frame.image if plan is None else plan.input_mosaic(frame.image))


def as_mosaic(plan: ColourPlan | None, image: np.ndarray) -> np.ndarray:
    """`image` as the 2-D mosaic EDI runs on (unchanged without a plan)."""
    return image if plan is None else plan.input_mosaic(image)


def _restricted(pair: FramePair, keep: np.ndarray) -> FramePair:
    """The pair seen only at the pixels `keep` (flat bool): other pixels join its mask; a fresh estimator cache."""
    excluded = ~keep if pair.mask is None else (pair.mask | ~keep)
    return replace(pair, mask=excluded, cache={})


def channel_contrast(estimator: ConsistencyContrast, pairs: Sequence[FramePair], pattern: ColorFilter,
                     height: int, width: int, c_init: tuple[float, float], *, z_separate: float = 3.0) -> dict:
    """c per Bayer channel on the consecutive-frame pairs, and whether the data support it over one shared c.

    The shared c is estimated on all the pairs' pixels, each channel's on its own pixels (the others masked), and
    each channel's is compared with the shared one on that channel's pixels: z = the cost decrease over its
    standard error (the consistency estimator's rule for c_on vs c_off). Per-channel c is supported when some
    channel beats the shared c by `z_separate`. Returns {"shared": (c_on, c_off) or None, "channels": {"B":
    (c_on, c_off) or None, "G": ..., "R": ...}, "z": {"B": z or None, ...}, "per_channel": bool}."""
    chan = channel_map(pattern, height, width).reshape(-1)
    shared = estimator.estimate(None, pairs, c_init)
    out: dict = {"shared": shared, "channels": {}, "z": {}, "per_channel": False}
    if shared is None:
        return out
    # like for like: a channel's c_on and c_off are separate only where the shared estimate's are, so z measures
    # the channels' difference and not the ON/OFF one
    estimator = replace(estimator, separate=shared[0] != shared[1])
    for k, name in enumerate(CHANNEL_NAMES):
        sub = [_restricted(p, chan == k) for p in pairs]
        est = estimator.estimate(None, sub, shared)
        z = None if est is None else estimator.compare(sub, shared, [est])
        out["channels"][name], out["z"][name] = est, z
        if z is not None and z >= z_separate:
            out["per_channel"] = True
    return out
