"""Scene activity: do the events show something changing, or only the sensor's background noise?

The worker's static-scene policy asks this of every event it reads: on a still scene a real sensor keeps firing
(0.1-5 events/s per pixel of background activity), and counting events alone turned that noise into a deblur
per APS frame and a latent frame every N events.

The test is spatial and calibrates itself. Background noise fires every pixel independently, so an event rarely
has a neighbour that fired shortly before it: with a per-pixel rate r, the chance is p = 1 - exp(-8 r dt). An
edge or a light change fires neighbouring pixels together, so most of its events are "supported". Per window of
sensor time, with n events (r estimated from n itself, as if they were all noise) and s of them supported, the
scene is active when s exceeds the noise expectation n p by `sigmas` binomial standard deviations plus a margin,
or when n alone is more than `max_noise_hz` per pixel gives.

Every verdict depends on the event stream alone, never on how it was cut into reads: a window is a run of
`check_us` spans of the event clock (aligned to multiples of `check_us`), judged at the end of each span that
held events, and its verdict falls at the first event of a later span. The window restarts after an active
verdict or once it covers `window_us`. Every event goes through the filter (~4 ns each; skipping it for busy
reads made the filter's state, and so later verdicts, depend on where the reads were cut); the windows are
counted in one compiled pass per read (edi.activity_verdicts). Limits: a small object
moving slower than a pixel per `support_us` fires no neighbours together and looks like noise (the heartbeat
still shows it); many hot pixels raise the supported count around them.
"""

from __future__ import annotations

import numpy as np

from edi_live import edi
from edi_live.datatypes import Frame


class SceneActivity:
    """Feed it every event in time order (`update`); ask `active_since(t)` whether a span judged active ended
    at or after sensor time t (µs)."""

    def __init__(self, width: int, height: int, *, window_us: int = 10_000, check_us: int = 1_000,
                 support_us: int = 5_000, max_noise_hz: float = 5.0, sigmas: float = 5.0, margin: int = 6) -> None:
        self.width, self.height = width, height
        self.window_us, self.check_us, self.support_us = window_us, check_us, support_us
        self.max_noise_hz, self.sigmas, self.margin = max_noise_hz, sigmas, margin
        self._last_t = edi.new_activity_map(width, height)
        self._state = edi.new_activity_state()  # the current window (edi.activity_verdicts)
        self._scratch: list = []  # its buffers
        self.last_active_us: int | None = None  # end of the latest span judged active
        self.windows = 0
        self.active_windows = 0

    def update(self, events: np.ndarray) -> list[tuple[int, bool, int]]:
        """Account for time-ordered events. Returns the verdicts that fell among them, in order: (index of the
        event from which it holds, active, end of the span judged)."""
        at, active, end = self.verdicts(events)
        return list(zip(at.tolist(), active.tolist(), end.tolist()))

    def verdicts(self, events: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """update() as arrays: (indices, active, span ends)."""
        if len(events) == 0:
            return np.empty(0, np.int64), np.empty(0, np.bool_), np.empty(0, np.int64)
        at, active, end = edi.activity_verdicts(events, self.width, self.height, self._last_t, self._state,
                                                check_us=self.check_us, window_us=self.window_us,
                                                max_noise_hz=self.max_noise_hz, sigmas=self.sigmas,
                                                margin=self.margin, support_us=self.support_us,
                                                scratch=self._scratch)
        if active.any():
            self.last_active_us = int(end[np.flatnonzero(active)[-1]])
        self.windows, self.active_windows = int(self._state[4]), int(self._state[5])
        return at, active, end

    def active_since(self, t_us: int | None) -> bool:
        """Whether a span judged active ended at or after t_us (None: ever)."""
        if self.last_active_us is None:
            return False
        return t_us is None or self.last_active_us >= t_us


class StaticScene:
    """The worker's static-scene state around SceneActivity: whether the scene was active since the latest
    deblurred APS frame, and per event whether it is only noise, an onset, or part of activity that went on
    within `hold_us` (sensor time). Both are functions of the event stream, not of the reads."""

    def __init__(self, hold_us: int = 50_000, fresh_us: int = 1_000) -> None:
        self.hold_us = hold_us
        # within the hold, events more than fresh_us after the latest active span's end are "held": active for the
        # event count, but what follows motion is mostly noise, which the worker's time rule must not show
        self.fresh_us = fresh_us
        self.activity: SceneActivity | None = None  # sized by the first APS frame
        self.active = True  # the state of the latest event (until the first verdict: active, not an onset)
        self.ref_end_us: int | None = None  # exposure end of the latest deblurred APS frame, in the event clock
        self.changed = True  # active between the previous deblurred frame and the current one
        self.noise_only_events = 0
        self._last_active_us: int | None = None  # the latest active verdict in force at the next event
        self._judged = False  # a verdict fell since the activity test started

    @property
    def quiet(self) -> bool:
        """The latest events showed only noise (False before the first APS frame: nothing is judged then)."""
        return self.activity is not None and not self.active

    def active_since_reference(self) -> bool:
        return self.activity is None or self.activity.active_since(self.ref_end_us)

    def new_reference(self, frame: Frame, anchor: bool = False) -> None:
        """An APS frame is deblurred: remember whether the scene changed since the previous one (`anchor`: it
        re-anchors the state after a gap, which counts as a change). `frame` in the event clock (frame_gate's
        in_event_clock): activity is judged on event times."""
        self.changed = anchor or self.active_since_reference()
        self.ref_end_us = frame.exposure_end_us
        if self.activity is None:
            self.activity = SceneActivity(frame.image.shape[1], frame.image.shape[0])

    def segments(self, events: np.ndarray) -> list[tuple[int, int, str]]:
        """The events cut where their state changes: (start, stop, "noise" | "onset" | "active" | "held").
        "noise": no frame is due for them; "onset": the first events of activity after noise; "held": within the
        hold but more than fresh_us after the latest active span (frames by event count only)."""
        n = len(events)
        if self.activity is None:
            return [(0, n, "active")] if n else []
        t = events["t"]
        states: list[tuple[int, int, str]] = []
        pos = 0
        at, active, end = self.activity.verdicts(events)
        if self._judged and not active.any() and (self._last_active_us is None
                                                  or t[0] > self._last_active_us + self.hold_us):
            self.noise_only_events += n  # the still scene's reads: noise, and noise before them
            self.active = False
            return [(0, n, "noise")]
        if n and self._judged and self._last_active_us is not None and self._within(t, at[active], end[active],
                                                                                    self.fresh_us):
            if active.any():
                self._last_active_us = int(end[active][-1])
            out = [(0, n, "active" if self.active else "onset")]  # a busy scene's reads: one active segment
            self.active = True
            return out
        # a noise verdict changes nothing once one fell: the hold runs out by time alone
        keep = np.flatnonzero(active) if self._judged else np.arange(len(at))
        verdicts = list(zip(at[keep].tolist(), active[keep].tolist(), end[keep].tolist()))
        for at_i, verdict, end_i in verdicts + [(n, None, 0)]:
            if pos < at_i:
                last = self._last_active_us
                if not self._judged:
                    cut = fresh = at_i
                elif last is None:
                    cut = fresh = pos
                else:  # active while the latest active span ended less than hold_us before the event
                    cut = pos + int(np.searchsorted(t[pos:at_i], last + self.hold_us, "right"))
                    fresh = pos + int(np.searchsorted(t[pos:cut], last + self.fresh_us, "right"))
                states += [(pos, fresh, "active"), (fresh, cut, "held"), (cut, at_i, "noise")]
            if verdict is not None:
                self._judged = True
                if verdict:
                    self._last_active_us = end_i
            pos = at_i
        out: list[tuple[int, int, str]] = []
        for lo, hi, kind in states:
            if lo >= hi:
                continue
            active = kind != "noise"
            if not active:
                self.noise_only_events += hi - lo
            elif not self.active:
                kind = "onset"
            if out and (out[-1][2] == kind or out[-1][2] == "onset" and kind == "active"):
                out[-1] = (out[-1][0], hi, out[-1][2])
                continue
            out.append((lo, hi, kind))
            self.active = active
        return out

    def _within(self, t: np.ndarray, at: np.ndarray, end: np.ndarray, hold: int) -> bool:
        """Whether every event is within `hold` µs of the active verdict in force at it (`at`/`end`: this read's
        active verdicts; before the first, the latest before the read): with fresh_us, the loop of segments()
        would make one active segment of them all. Events before a verdict lie in spans before its end, so
        consecutive verdict ends at most `hold` apart are enough between verdicts (False when they are not: the
        loop decides)."""
        last = self._last_active_us
        if at.size == 0:
            return int(t[-1]) <= last + hold
        if (at[0] > 0 and int(t[at[0] - 1]) > last + hold) or int(t[-1]) > int(end[-1]) + hold:
            return False
        return end.size < 2 or int(np.diff(end).max()) <= hold
