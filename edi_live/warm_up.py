"""Compiling (or loading from the on-disk cache) every numba kernel a run will need, before the source streams:
a kernel met with new argument types mid-stream compiles on the spot, seconds with a cold cache, while a live
camera's data pile up. Runs a throwaway reconstructor and the worker's activity test over tiny synthetic input."""

from __future__ import annotations

import logging
import math
import threading
from typing import Any, Callable

import numpy as np

from edi_live import kernel_cache
from edi_live.datatypes import EVENT_DTYPE, Frame

log = logging.getLogger("edi_live.node")


SLOW_NOTICE = ("compiling the EDI kernels (numba) before the input opens: 15-30 s on the first run after installing "
               "or upgrading; later runs load them from the cache in under a second")


def warm_up(make_reconstructor: Callable[..., Any], edi_config: Any, slow_after_s: float = 2.0) -> None:
    """Run a throwaway reconstructor over a tiny synthetic scene before the source starts.

    The EDI kernels are numba functions: compiled on first use (15-30 s in all, with a cold cache) or loaded from
    the on-disk cache (~0.4 s). Paying that here, before a camera streams or the replay clock starts, keeps the first
    APS frames from stalling the worker while the ring fills (a live camera would drop data). A failure here is
    not fatal: the real run reports it where it happens. Past `slow_after_s` one line says why the start waits
    (a first run printed nothing at all for that long).
    """
    cache_notice = kernel_cache.notice()
    if cache_notice:  # the kernels are cached where the next start may not find them: say so once
        log.warning(cache_notice)
    timer = threading.Timer(slow_after_s, log.info, args=(SLOW_NOTICE,))
    timer.daemon = True
    timer.start()
    try:
        _exercise(make_reconstructor, edi_config)
    finally:
        timer.cancel()


def _exercise(make_reconstructor: Callable[..., Any], edi_config: Any) -> None:
    width, height = 16, 12
    rng = np.random.default_rng(0)
    image = np.full((height, width), 100, np.uint8)
    frozen = image.copy()
    frozen.setflags(write=False)  # numba compiles read-only arrays separately (a decoded frame can be one)
    try:
        from edi_live import edi

        rec = make_reconstructor(width, height, edi_config)
        t_us = 0
        for k in range(3):  # three frames: the c estimator needs frame pairs
            events = np.zeros(200, EVENT_DTYPE)
            events["t"] = np.sort(rng.integers(t_us, t_us + 20_000, events.size))
            events["x"] = rng.integers(0, width, events.size)
            events["y"] = rng.integers(0, height, events.size)
            events["p"] = rng.integers(0, 2, events.size).astype(bool)
            rec.on_frame(Frame(image if k % 2 == 0 else frozen, t_us, t_us + 10_000), events)
            later = events[events["t"] > t_us + 10_000]
            rec.on_events(later[:-1])
            rec.on_events(later[-1:])  # one event: its field views count as C-contiguous, another specialisation
            rec.render()
            t_us += 20_000
        # fused mode's plan and propagation kernels, from two references; nearest mode renders the frames it holds at
        # a stream's end with the same propagation
        if edi_config.mode in ("fused", "nearest"):
            from edi_live.datatypes import concat_events

            previous = rec.reference_log()
            later = events.copy()
            later["t"] += 20_000
            rec.on_frame(Frame(image, t_us, t_us + 10_000), later)
            both = concat_events([events, later])
            rec.render_fused(previous, image, image, [previous[1] + 5_000, t_us + 4_000], both)
            # again on strided event fields: the reconstructor may have judged the random events a still scene
            for residual in (False, True):  # the per-frame path, and the residual estimate's one-call kernels
                edi.fused_frames(rec.reference_log(), previous, (image > 0, image > 0), [previous[1] + 5_000], both,
                                 (0.2, 0.2), None, residual=residual)
            t_us += 20_000
        # the worker's time rule for latent frames: its compiled pass over a ring slice's times (strided), and over
        # one event's (contiguous)
        from edi_live.frame_cadence import FrameCadence

        for times in (events["t"], events["t"][-1:]):
            FrameCadence(1, 1).cuts(times, 0)
        # the running double integral (deblur ahead): fed ring slices (strided fields) and single events
        npix = width * height
        t_lo, t_hi = int(events["t"][0]), int(events["t"][-1])
        for c_off in (0.2, 0.15):
            for mask, counts in ((None, None), (np.zeros(npix, bool), np.zeros(npix, np.int64))):
                run = edi.RunningDivisor(width, height, t_lo, t_hi, (t_lo + t_hi) // 2, 0.2, c_off, mask=mask,
                                     event_counts=counts)
                run.feed(events[:-1])
                run.remask(None if mask is None else ~mask, events)  # flagged / released on the way: its pixel pass
                run.feed_from(events[-1:])
                run.finish((np.zeros(npix, np.int64), np.zeros(npix, np.int64)) if counts is not None else None)
        # the smoothed deblur (edi/smoothing.py): its median, and the frame finish that shows it, for a writeable
        # and a read-only (decoded) frame
        pix, zeros = np.arange(4, dtype=np.int64), np.zeros(4)
        shown = edi.smoothed_divisor((pix, zeros, zeros), width, height)
        for frame_image in (image, frozen):
            logs = [np.empty((height, width), np.float32) for _ in range(3)]
            edi.finish_frame_u8(frame_image, 255.0, (pix, zeros, zeros), logs[0], np.empty((height, width), np.uint8),
                                logs[1], np.empty((height, width), np.uint8), shown=shown, log_shown=logs[2])
        # its re-mask picks a released pixel's events with the pixel-sample kernel, which with a fixed c (no c
        # tracker) nothing else has compiled: ring slices, one event, none
        for batch in (events, events[-1:], events[:0]):
            edi.events_at_pixels(batch, width, height, np.ones(npix, bool), t_lo, t_hi)
        # exposures without events (a dark or still scene), first and later: empty field views count as
        # C-contiguous, another specialisation; a frame without events takes the per-pixel frame finish (no
        # median), which a read-only frame meets nowhere else once the median is on
        empty = np.zeros(0, EVENT_DTYPE)
        for frame_image in (image, frozen):
            rec.on_frame(Frame(frame_image, t_us, t_us + 10_000), empty)
            t_us += 20_000
        first = make_reconstructor(width, height, edi_config)
        for k in range(3):
            first.on_frame(Frame(image if k % 2 == 0 else frozen, k * 20_000, k * 20_000 + 10_000), empty)
        # separate thresholds have their own single-pass divisor kernel: the first estimate with c_on != c_off
        # must not compile it mid-stream
        t0 = int(events["t"][0])  # an exposure over these events (fused mode's block above moved t_us on)
        edi.log_divisor_events(events, width, height, t0, t0 + 10_000, None, 0.2, 0.15)
        # the worker's noise-or-activity test: its filter kernel over ring slices (strided fields) and one event
        from edi_live.activity import SceneActivity

        activity = SceneActivity(width, height)
        activity.update(events[:10])
        activity.update(events[10:11])
        # the prediction figure (its frame average; the pixels with events, on ring slices and one event), the
        # black-level profile (its first fit comes frames later) and the unreliable-pixel mask's dilation (only
        # once a pixel is flagged, which the scene above never does)
        from edi_live.contrast import _kernels_black_level, _kernels_clock_offset
        from edi_live.hold_average import hold_average

        hold_average([image, image], [1, 1], 2)
        marks = np.zeros(npix, bool)
        edi.mark_event_pixels(events[:10], width, height, marks)
        edi.mark_event_pixels(events[10:11], width, height, marks)
        b = np.linspace(5.0, 200.0, 64)
        _kernels_black_level.profile_point(b, b + 1.0, np.ones(64), 2.0, 0.5, 5, 50.0, math.inf)
        # the clock-offset fit's lookup: the scene above is still (random events), and still pairs are not fitted
        one = np.zeros(1, np.int64)
        _kernels_clock_offset.integrals_at(np.array([0, 5], np.int64), np.array([0, 2], np.int64), one,
                                           np.array([1, 3], np.int64), np.zeros(2), np.ones(2), 0)
        edi.dilate(np.zeros((height, width), bool), [(0, 0), (0, 1)])
        # a colour source's output demosaic: of the latent display, and of a decoded (read-only) APS frame
        from edi_live.colour import demosaic

        demosaic(image, "RGGB")
        demosaic(frozen, "RGGB")
        logs, shown = np.zeros((2, height, width), np.float32), np.zeros((2, height, width), np.uint8)
        for frame in (image, frozen):  # B of a frame with a black level (its look-up; the scene above has none)
            edi.blurry_to_float(frame, black_level=1.0)  # and the fall-back to the APS at unreliable pixels
            edi.fall_back_u8(np.zeros((height, width), bool), frame, 0.0, 1.0, logs[0], logs[1], shown[0], shown[1])
    except Exception:  # noqa: BLE001 - warm-up only; see docstring
        log.debug("kernel warm-up failed", exc_info=True)


def compiled_signatures() -> dict[str, set[str]]:
    """Each numba kernel's compiled argument-type signatures so far, across the packages (edi_live.edi's own
    kernels, the compiled parts of the calibration and the prediction figure, the colour demosaic and the worker's
    frame cadence): what a warm-up must cover."""
    from edi_live import _kernels_demosaic, edi, frame_cadence, hold_average
    from edi_live.contrast import _kernels_black_level, _kernels_clock_offset

    return edi.compiled_signatures(also=(_kernels_black_level, _kernels_clock_offset, hold_average,
                                         _kernels_demosaic, frame_cadence))

