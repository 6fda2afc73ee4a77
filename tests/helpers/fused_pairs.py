"""Fused frames against the simulator's truth: the loop the fused-mode tests share."""

from __future__ import annotations

from typing import Iterator

import numpy as np


def fused_at_truth(sim, rec) -> Iterator[tuple[int, int, object, tuple, tuple]]:
    """Deblur every APS frame of `sim` with `rec` and render the fused frames at the ground truth's latent times
    between each pair: yields (ground-truth index, t, fused Reconstruction, previous (log L, f), current (log L, f))."""
    ev = sim.events
    prev = None
    for k, f in enumerate(sim.frames):
        i0, i1 = np.searchsorted(ev["t"], [f.exposure_start_us, f.exposure_end_us + 1])
        rec.on_frame(f, ev[i0:i1])
        cur = rec.reference_log()
        if prev is not None:
            gts = [g for g in np.flatnonzero(sim.gt_kind == 1) if sim.gt_frame[g] == k - 1]
            times = [int(sim.gt_t_us[g]) for g in gts]
            frames = rec.render_fused(prev, sim.frames[k - 1].image, f.image, times, ev)
            for g, t, r in zip(gts, times, frames):
                yield g, t, r, prev, cur
        prev = cur
