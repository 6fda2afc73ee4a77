"""Which of the steady-state calibration checks run on an APS frame: every frame while the calibration is young or
has just changed, fewer once it has settled.

Policy only (no math, no clock, no thread): frame_calibration asks it per frame and tells it afterwards whether
the frame was calm. A frame is calm when the c policy passed its fit test (or had none due) without estimating,
the black level and clock offset did not move, the frame closed a pair, and the events are not ignored (a still
scene's test is what notices that it moves again: the latent frames stand still until then). After
`calm_frames` calm frames in a row the schedule thins out; a change (an estimate, a new black level or offset, a
gap) brings back every frame at once, until `calm_frames` calm frames have passed again; a fit test that fails
without a change yet (the c policy waits for a second failure in a row) brings back every frame until the next
calm frame.

Thinned, with k counting the frames since thinning began (k = 0, 1, 2, ...):
- the c fit test runs on every `c_every`-th frame (k = c_every - 1, 2 c_every - 1, ...): a failure ends the
  thinning, so the fit test's patience (two failures in a row) runs on consecutive frames as before;
- the c estimator's level table of a frame is built only where a fit test will read it: on the tested frame and on
  the one before it (the pair it tests; frame_calibration asks `plan()` of the next frame), and where the black
  level's pool samples the pair.
Not thinned: the unreliable-pixel and hot-pixel masks (they change frames directly), the pixel-noise statistics
(two pairs merged into one interval read rates 16 % low on a still scene with 20 Hz of shot noise: the still
test over a longer interval is not the same test; skipping pairs halves the observation time), the black level's
and clock offset's own schedules (a recheck every 100 and 1000 frames: nothing to thin between them).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ScheduleSettings:
    calm_frames: int = 8  # calm frames in a row before the checks thin out
    c_every: int = 1  # thinned: a c fit test on every this-many-th frame (1: every frame, nothing thinned)


@dataclass(frozen=True)
class Plan:
    """What runs on one frame."""

    c_test: bool  # the c policy's fit test (an estimate when it fails, or when one is due anyway)


EVERY_FRAME = Plan(True)


class CalibrationSchedule:
    """`plan()` before a frame's checks, `observe(calm)` after them."""

    def __init__(self, settings: ScheduleSettings = ScheduleSettings()) -> None:
        if settings.c_every < 1 or settings.calm_frames < 0:
            raise ValueError(f"a calibration schedule needs c_every >= 1 and calm_frames >= 0 "
                             f"(got {settings})")
        self.settings = settings
        self._calm = 0  # calm frames in a row

    @property
    def enabled(self) -> bool:
        return self.settings.c_every > 1

    @property
    def thinned(self) -> bool:
        return self.enabled and self._calm >= self.settings.calm_frames

    def plan(self) -> Plan:
        """The frame's plan; asking again before observe() gives the same answer (it peeks at the next frame)."""
        if not self.thinned:
            return EVERY_FRAME
        s = self.settings
        return Plan((self._calm - s.calm_frames) % s.c_every == s.c_every - 1)

    def observe(self, calm: bool, changed: bool = True) -> None:
        """After a frame's checks: `calm` (nothing changed, nothing pending) or not; a frame that is not calm but
        `changed` nothing (a fit test failed once, c kept) brings back every frame only until a calm frame: its
        next test, on the next frame, either confirms the failure (an estimate: changed) or resumes thinning."""
        if calm:
            self._calm += 1
        elif changed:
            self._calm = 0
        else:
            self._calm = min(self._calm, self.settings.calm_frames - 1)
