"""The deblur's correction smoothed across neighbouring pixels: a 3x3 median of log D.

Why: EDI divides each pixel's B by its own double integral D, which its own events alone decide. A pixel's event
count carries errors its neighbours do not share (its threshold's mismatch, a noise event, an event lost to the
refractory period, where its log intensity sat in its dead band when the exposure began), so the correction is
right on average and speckled pixel by pixel. Neighbouring pixels see the same motion, so the median of log D
over a pixel and its 8 neighbours keeps the correction of an edge (a median keeps steps) and drops a lone pixel's
error; an isolated noise event, among neighbours without events (log D = 0), is not divided out at all. B itself
is never filtered: only the correction is. On the simulators this gains ~2 dB on deblurred frames at mid-exposure
(ideal and realistic camera; docs/accuracy.md), and starting the latent image at te from the smoothed correction
(log L(te) = log B - median(log D - the f -> te exponent)) gains a few tenths on latent frames.

`step` 2 takes the neighbours of a pixel's own colour on a Bayer mosaic. The reconstructor does not smooth a
mosaic: its same-colour footprint spans 5x5 pixels, and on the colour benchmark the median cost 1.3 dB at f on
the blocks scene (mixing the channels, step 1, cost 2.7 dB).
"""

from __future__ import annotations

import numpy as np

from edi_live.edi import _backend, _kernels_smoothing


def new_median_scratch(width: int, height: int) -> np.ndarray:
    """Work space for smoothed_divisor, kept between frames (fresh arrays per frame cost more than the medians: their
    pages are new to the process): a zeroed float32 grid it leaves zeroed, and a dense output."""
    return np.zeros((2, width * height), np.float32)


def median_at_pixels(pixels: np.ndarray, values: np.ndarray, width: int, height: int, step: int = 1) -> np.ndarray:
    """At each of `pixels` (flat indices, unique), the median of `values` over its 3x3 neighbours `step` pixels apart
    (float64). A neighbour that is not in `pixels` counts as 0; one off the sensor counts as the pixel itself."""
    pixels, values = _checked(pixels, values, step)
    out = np.empty(pixels.size, np.float64)
    if pixels.size == 0:
        return out
    if _backend.have_numba():
        npix = width * height
        _kernels_smoothing.median_at(pixels, values, int(width), int(height), int(step), np.zeros(npix),
                                     np.empty(npix), out)
        return out
    grid = np.zeros(width * height, np.float64)
    grid[pixels] = values
    y, x = np.divmod(pixels, width)
    stack = []
    for dy in (-step, 0, step):
        yy = np.where((y + dy < 0) | (y + dy >= height), y, y + dy)
        for dx in (-step, 0, step):
            xx = np.where((x + dx < 0) | (x + dx >= width), x, x + dx)
            stack.append(grid[yy * width + xx])
    return np.median(np.stack(stack), axis=0)


def smoothed_divisor(divisor: tuple[np.ndarray, np.ndarray, np.ndarray | None], width: int, height: int,
                     step: int = 1, *, scratch: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(the median of log D at the active pixels, the jump from there to the median of the log divisor at te, or
    None without an f -> te exponent) for a (pixels, log D, f -> te exponent) divisor of log_divisor_events, both
    float32: the values the frame finish reads (a median of float32-rounded values is the rounded median, so
    nothing is lost). `scratch`: new_median_scratch(width, height)."""
    pixels, log_d, delta_end = divisor
    pixels, log_d = _checked(pixels, log_d, step)
    if delta_end is None:
        return median_at_pixels(pixels, log_d, width, height, step).astype(np.float32), None
    delta_end = np.asarray(delta_end, np.float64)
    if scratch is not None and (scratch.dtype != np.float32 or scratch.shape != (2, width * height)):
        raise ValueError(f"scratch must be new_median_scratch({width}, {height}): (2, {width * height}) float32 "
                         f"(got {scratch.shape} {scratch.dtype})")
    if not _backend.have_numba():
        shown = median_at_pixels(pixels, log_d, width, height, step).astype(np.float32)
        at_te = median_at_pixels(pixels, (log_d - delta_end).astype(np.float32), width, height, step)
        return shown, shown - at_te.astype(np.float32)
    if scratch is None:
        scratch = new_median_scratch(width, height)
    shown, jump = np.empty(pixels.size, np.float32), np.empty(pixels.size, np.float32)
    if pixels.size:
        _kernels_smoothing.smoothed_pair(pixels, log_d, delta_end, int(width), int(height), int(step), scratch[0],
                                         scratch[1], shown, jump)
    return shown, jump


def _checked(pixels: np.ndarray, values: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    pixels, values = np.asarray(pixels, np.int64), np.asarray(values, np.float64)
    if pixels.size != values.size:
        raise ValueError(f"one value per pixel (got {values.size} values for {pixels.size} pixels)")
    if step < 1:
        raise ValueError(f"the neighbours' step must be at least 1 (got {step})")
    return pixels, values
