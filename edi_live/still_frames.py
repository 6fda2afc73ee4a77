"""What a still scene does without, on the sensor clock: a deblurred frame not worth sending, an APS frame not worth
deblurring, and the heartbeat frame that still comes once per `heartbeat_s` of sensor time.

Plain state that the worker thread owns and updates; whether the events show activity or only noise is
edi_live.activity's verdict. Everything here follows event and exposure times, never the host clock, so that a
replay makes the same frames however its reads are cut (docs/node.md, "Replay determinism").
"""

from __future__ import annotations

import numpy as np

from edi_live.activity import StaticScene
from edi_live.datatypes import Frame

APS_CHANGE_DN = 8  # without events: a pixel changed when its APS value moved by more than this (read noise: 1-3 DN)
APS_CHANGED_FRACTION = 0.001  # ... and the frame changed when more than this share of its pixels did
STATIC_EVENTS = 16  # fewer events than this in an exposure (and since the last frame) = a static scene
MOVING_EVENTS_CAP = 100  # the threshold at the default --every 1000; larger --every values do not raise it
_T_MIN = -np.iinfo(np.int64).max


class StillFrames:
    def __init__(self, every: int, heartbeat_s: float) -> None:
        self.every = every
        self.heartbeat_us = int(heartbeat_s * 1e6)
        self.last_deblur_us: int | None = None  # exposure end of the latest deblurred APS frame
        self.last_emit_t = _T_MIN  # t_us of the latest frame sent
        # events of an active scene since the latest deblurred APS frame (the worker's `since` counts from the latest
        # frame, which the --every-ms rule makes a few ms old at most: too short a view of whether the scene moved)
        self._streamed = 0
        self._streamed_before = 0  # ... up to the latest deblurred APS frame, for its send decision
        self._last_image: np.ndarray | None = None  # the latest deblurred APS frame's image

    def moving(self, n_exposure_events: int, since: int, scene: StaticScene, events_seen: bool = True) -> bool:
        """Whether a deblurred frame is worth sending: the scene was active, and a tenth of a latent frame's events
        (capped: a huge --every cannot hide moving frames) came during its exposure or since the last frame. Without
        any event seen (`events_seen` False), every deblurred frame is: skip_deblur already kept out the unchanged
        ones."""
        if not events_seen:
            return True
        threshold = max(STATIC_EVENTS, min(self.every // 10, MOVING_EVENTS_CAP))
        since = max(since, self._streamed_before)
        return (n_exposure_events >= threshold or since >= threshold) and scene.changed

    def skip_deblur(self, frame: Frame, n_events: int, since: int, scene: StaticScene,
                    events_seen: bool = True) -> bool:
        """A static scene: (almost) no events, or only noise, since the previous deblur, so L(f) would be the
        current reference up to sensor noise. The events keep the latent image right; a real deblur is still
        forced every heartbeat_s of sensor time to bound drift. This is what keeps a still camera near zero CPU.
        A source that sent no event at all (`events_seen` False: frames only, or a DVS switched off) cannot say
        whether the scene moved: its APS frames do (_aps_unchanged). Ask only with a reference in use."""
        if self.last_deblur_us is None or frame.exposure_end_us - self.last_deblur_us >= self.heartbeat_us:
            return False  # the heartbeat's deblur
        if not events_seen:
            return self._aps_unchanged(frame)
        since = max(since, self._streamed)
        return not ((n_events >= STATIC_EVENTS or since >= STATIC_EVENTS) and scene.active_since_reference())

    def _aps_unchanged(self, frame: Frame) -> bool:
        """The APS frame shows what the latest deblurred one showed: at most APS_CHANGED_FRACTION of its pixels
        moved by more than APS_CHANGE_DN."""
        last = self._last_image
        if last is None or last.shape != frame.image.shape:
            return False
        moved = np.abs(frame.image.astype(np.int32) - last.astype(np.int32)) > APS_CHANGE_DN
        return np.count_nonzero(moved) <= APS_CHANGED_FRACTION * moved.size

    def streamed(self, n: int) -> None:
        """n events of an active scene went to the latent image (not noise)."""
        self._streamed += n

    def deblurred(self, frame: Frame) -> None:
        self.last_deblur_us = frame.exposure_end_us
        self._last_image = frame.image
        self._streamed_before, self._streamed = self._streamed, 0

    def emitted(self, t_us: int) -> None:
        self.last_emit_t = max(self.last_emit_t, t_us)

    def heartbeat_at(self, t: np.ndarray, lo: int, hi: int) -> int:
        """The first of events [lo, hi) at or after the next heartbeat's sensor time, or hi."""
        due = self.last_emit_t + self.heartbeat_us
        return lo + int(np.searchsorted(t[lo:hi], due)) if due <= t[hi - 1] else hi

    def heartbeat_due(self, t_us: int) -> bool:
        """No frame came from the latest one up to sensor time t_us."""
        return self.last_emit_t + self.heartbeat_us <= t_us
