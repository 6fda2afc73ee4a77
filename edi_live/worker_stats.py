"""The worker's counters for the stats map (edi_live.stats.collect): what it read, sent and skipped, its deblur
times, and the reconstructor's and the prediction figure's numbers. Safe to call from any thread (it reads plain
values the worker thread writes)."""

from __future__ import annotations

from typing import Any

import numpy as np

from edi_live.deblur_handover import StreamingCopy
from edi_live.reconstructor_stats import reconstructor_stats


def worker_stats(worker: Any) -> dict[str, Any]:
    """The EdiWorker's stats() (worker.py imports this module, not the other way round)."""
    deblur = list(worker._deblur_ms)
    rec = worker.rec  # one read: the worker thread swaps it at each hand-over
    if isinstance(rec, StreamingCopy):  # a deblur is pending: describe the original, not the copy
        rec = rec.original
    return {
        "events_processed": worker.events_in,
        "aps_frames_in": worker.frames_in,
        "frames_deblurred": worker.sent.get("deblurred", 0),
        "frames_latent": worker.sent.get("latent", 0),
        "heartbeats": worker.heartbeats, "skipped_static": worker.skipped_static,
        "skipped_static_deblur": worker.skipped_static_deblur, "quiet_waits": worker._quiet.batched_waits,
        "noise_only_events": worker._scene.noise_only_events,
        "skipped_max_fps": worker.skipped_max_fps, "frames_not_rendered": worker.demand.not_rendered,
        "worker_gaps": worker.gaps,
        "worker_busy_s": round(worker.busy_s, 3),
        "deblur_ms_p50": round(float(np.median(deblur)), 3) if deblur else None,
        "deblur_ms_max": round(float(np.max(deblur)), 3) if deblur else None,
        "nearest_added_latency_ms_p50": worker._nearest.waited_ms_p50() if worker.config.mode == "nearest" else None,
        "fused_added_latency_ms_p50": worker._nearest.waited_ms_p50() if worker.config.mode == "fused" else None,
        # c, camera values, ignored pixels, noise statistics (up to date once the worker has finished)
        **reconstructor_stats(rec, current=worker.done.is_set()),
        **(worker.quality.stats() if worker.quality is not None else {}),
    }
