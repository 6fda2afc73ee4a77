"""The Event-based Double Integral (EDI, Pan et al. CVPR 2019) as pure functions on numpy arrays.

Owns: the per-frame level table, the exact normalised double integral, deblurring one APS frame, and latent
propagation. No I/O, no threads, no state beyond the arguments. Times are int64 µs; intensities are float on
the 8-bit APS scale (0..255, linear).

Model, per pixel, for an APS frame with exposure [ts, te], T = te - ts, and reference time f in [ts, te]:

    log L(t) - log L(f) = c_on * n_on(f->t) - c_off * n_off(f->t)        (n counts signed: negative for t < f)
    B = (1/T) * integral_ts^te L(t) dt = L(f) * D(c),   D(c) = (1/T) * integral exp(c_on*n_on - c_off*n_off) dt

E(t) is piecewise constant between a pixel's events, so D(c) is an exact finite sum over the states the pixel
visited, weighted by the time spent there:  D(c) = sum_k (dwell_k / T) * exp(c_on*on_k - c_off*off_k).
`build_level_table` collects those dwell times once per frame in O(events); `log_divisor` then evaluates log D for
any (c_on, c_off) in O(active pixels x levels) without touching events again. Pixels without events in the
exposure have D = 1 and are never computed.

Window convention (half-open in the usual sense, closed at the exposure ends):

    ts ------[seg 0)----- e1 -----[seg 1)----- e2 ---- ... ---- ek -----[seg k]----- te
    an event at exactly f counts as "before f" (the segment that contains f has level 0).

This package is the EDI math's one public surface: import it as `import edi_live.edi as edi` and use the names
below; its underscored modules (the numba kernels) are private. Every function runs a compiled kernel and keeps a
numpy reference of the same contract (`numpy_reference()`, see _backend).

Modules: selection (time windows, pixel picks, counts), levels (level table, log D), deblur (log L(f)), smoothing (the
3x3 median of log D), lone (lone changes in latent frames), latent (propagation, rendering), fused (two-frame latent
images), pixels (hot pixels, noise and flicker filters, sampling), pairs (the consistency estimator's sums), running
(the double integral of an exposure accumulated while its events arrive).
"""

from types import ModuleType

from edi_live.edi import (_kernels_fused, _kernels_levels, _kernels_pixels, _kernels_residual, _kernels_schedule,
                          _kernels_lone, _kernels_smoothing, _kernels_stream)
from edi_live.edi._backend import (DARK_FLOOR, LEVEL_CAP, LOG_MAX, LOG_MIN, have_numba, numpy_reference)
from edi_live.edi.deblur import (ApsResponse, blurry_to_float, deblur, deblur_log, fall_back_u8, finish_frame_u8,
                                 log_divisor_events, reference_logs)
from edi_live.edi.fused import (RESIDUAL_SPAN, FusedPropagator, FusionPlan, event_mass, forward_plan, fused_frames,
                                fused_log, fusion_plan, fusion_weights, time_share)
from edi_live.edi.residual_schedule import COLD_CONTEXT as RESIDUAL_COLD_CONTEXT, ResidualCarry
from edi_live.edi.latent import (Propagator, event_delta, propagate_log, render_buckets, to_uint8, u8_tables)
from edi_live.edi.levels import LevelTable, build_level_table, empty_table, log_divisor, rows_of
from edi_live.edi.pairs import consistency_cost, pair_candidates
from edi_live.edi.running import RunningDivisor
from edi_live.edi.lone import LoneChanges, lone_changes_u8
from edi_live.edi.smoothing import median_at_pixels, new_median_scratch, smoothed_divisor
from edi_live.edi.pixels import (FlickerState, activity_verdicts, background_activity_keep, decay_hot_counts, dilate,
                                 flicker_cycles, hot_pixel_mask, isolated_event_mask, mark_event_pixels,
                                 new_activity_map, new_activity_state,
                                 supported_events_keep, update_contradictions)
from edi_live.edi.selection import (add_counts, events_at_pixels, flat_index, select, signed_counts, time_index,
                                    window)



def compiled_signatures(also: tuple[ModuleType, ...] = ()) -> dict[str, set[str]]:
    """Each kernel's compiled argument-type signatures so far (to check that a warm-up covered what a run needs:
    a kernel met with new argument types compiles on the spot, which stalls a stream); `also`: other modules whose
    compiled functions count too."""
    found = {}
    for module in (_kernels_fused, _kernels_levels, _kernels_pixels, _kernels_residual, _kernels_schedule,
                   _kernels_lone, _kernels_smoothing, _kernels_stream, *also):
        for name, fn in vars(module).items():
            signatures = getattr(fn, "signatures", None)
            if signatures is not None:
                found[f"{module.__name__.rsplit('.', 1)[-1]}.{name}"] = set(map(str, signatures))
    return found


__all__ = [
    "activity_verdicts", "add_counts", "ApsResponse", "background_activity_keep", "blurry_to_float",
    "build_level_table", "compiled_signatures", "consistency_cost", "DARK_FLOOR", "deblur", "deblur_log",
    "decay_hot_counts", "dilate", "empty_table", "event_delta", "event_mass", "events_at_pixels", "fall_back_u8",
    "finish_frame_u8", "flat_index", "flicker_cycles", "FlickerState", "forward_plan", "fused_frames", "fused_log",
    "FusedPropagator", "fusion_plan", "fusion_weights", "FusionPlan", "have_numba", "hot_pixel_mask",
    "isolated_event_mask", "LoneChanges", "lone_changes_u8", "LEVEL_CAP", "LevelTable", "log_divisor",
    "log_divisor_events", "LOG_MAX", "LOG_MIN",
    "mark_event_pixels", "median_at_pixels", "new_activity_map", "new_activity_state",
    "new_median_scratch",
    "numpy_reference", "pair_candidates", "propagate_log", "Propagator", "reference_logs", "render_buckets",
    "RESIDUAL_COLD_CONTEXT", "RESIDUAL_SPAN", "ResidualCarry", "rows_of", "RunningDivisor", "select",
    "signed_counts", "smoothed_divisor", "supported_events_keep", "time_index", "time_share", "to_uint8",
    "u8_tables", "update_contradictions", "window",
]
