"""`--mode fused` bookkeeping for the worker: every latent time after the current reference waits for the next
APS frame, then is rendered from both frames (EdiReconstructor.render_fused, the math in edi_live.edi.fused); the
previous reference (its log L(f) and APS image) is kept for that. Runs on the worker thread.

Latency: a frame at t waits until the next APS frame is deblurred, i.e. up to one frame interval plus half an
exposure after t; the wait is measured like nearest mode's (`fused_added_latency_ms_p50`).
"""

from __future__ import annotations

import numpy as np

from edi_live.nearest_mode import NearestHoldBack

_MAX_HELD = 4096  # beyond this (APS frames stopped coming), frames are rendered forward from the reference
# c is estimated jointly over this many consecutive frame pairs (edi_live.contrast.joint; the node sets it in
# fused mode): fewer re-estimations at scene cuts, and the frames wait for the next APS frame anyway
JOINT_PAIRS = 6


class FusedHoldBack(NearestHoldBack):
    def __init__(self) -> None:
        super().__init__()
        self.previous: tuple[tuple[np.ndarray, int], np.ndarray] | None = None  # ((log L(f), f), APS image)

    def should_hold(self, t_us: int, ref_f_us: int | None) -> bool:
        return ref_f_us is not None and t_us > ref_f_us and len(self.held) < _MAX_HELD

    def take_before(self, mid_us: int | None) -> list[tuple[int, int]]:
        return []  # nothing is rendered from the older reference alone

    def take_until(self, f_us: int) -> list[tuple[int, int]]:
        """The held times up to the new reference f (they lie between the two frames), removed from the hold."""
        done = [d for d in self.held if d[0] <= f_us]
        self.held = [d for d in self.held if d[0] > f_us]
        return done

    def gap(self) -> None:
        super().gap()
        self.previous = None  # never fuse across lost data
