"""The edi-worker's stats map (EdiWorker.stats): its counters, the reconstructor's and the quality score's.

Read from any thread: the counters are plain ints and floats the worker thread replaces.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from edi_live.reconstructor_stats import reconstructor_stats


def worker_stats(worker: Any) -> dict[str, Any]:
    """`worker`: an EdiWorker (its counters and parts, read as they are)."""
    deblur = list(worker._deblur_ms)
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
        **reconstructor_stats(worker.rec),  # c, camera values, ignored pixels, noise statistics
        **(worker.quality.stats() if worker.quality is not None else {}),
    }
