"""Scene activity: do the events show something changing, or only the sensor's background noise?

The worker's static-scene policy asks this per chunk of events: on a still scene a real sensor keeps firing
(0.1-5 events/s per pixel of background activity), and counting events alone turned that noise into a deblur
per APS frame and a latent frame every N events.

The test is spatial and calibrates itself. Background noise fires every pixel independently, so an event rarely
has a neighbour that fired shortly before it: with a per-pixel rate r, the chance is p = 1 - exp(-8 r dt). An
edge or a light change fires neighbouring pixels together, so most of its events are "supported". Per window of
sensor time, with n events (r estimated from n itself, as if they were all noise) and s of them supported, the
scene is active when s exceeds the noise expectation n p by `sigmas` binomial standard deviations plus a margin.
A window with significantly more events than `max_noise_hz` per pixel gives is active without the test, so
the per-event filter (edi.background_activity_keep) only ever runs at noise-like rates and costs nothing
measurable while the scene moves. Limits: a small object moving slower than a pixel per `support_us` fires no
neighbours together and looks like noise (the heartbeat still shows it); many hot pixels raise the supported
count around them.
"""

from __future__ import annotations

import math

import numpy as np

from edi_live import edi
from edi_live.datatypes import Frame


class SceneActivity:
    """Feed it every event in time order (`update`); ask `active_since(t)` whether a window judged active ended
    at or after sensor time t (µs)."""

    def __init__(self, width: int, height: int, *, window_us: int = 10_000, support_us: int = 5_000,
                 max_noise_hz: float = 5.0, sigmas: float = 5.0, margin: int = 6) -> None:
        self.width, self.height = width, height
        self.window_us, self.support_us = window_us, support_us
        self.max_noise_hz, self.sigmas, self.margin = max_noise_hz, sigmas, margin
        self._last_t = edi.new_activity_map(width, height)
        self._w0: int | None = None  # sensor time the current window started
        self._n = 0  # events in the current window
        self._s = 0  # of which supported (only while the filter runs)
        self._tested = 0  # of which went through the filter
        self.last_active_us: int | None = None  # end of the latest window judged active
        self.windows = 0
        self.active_windows = 0

    def update(self, events: np.ndarray) -> bool:
        """Account for a chunk of time-ordered events; True if the current window is (now) judged active."""
        n = len(events)
        if n == 0:
            return False
        t_end = int(events["t"][-1])
        if self._w0 is None:
            self._w0 = int(events["t"][0])
        self._n += n
        pixel_s = self.width * self.height * max(t_end - self._w0, 1_000) * 1e-6
        rate_hz = self._n / pixel_s
        most = self.max_noise_hz * pixel_s
        if self._n > most + self.sigmas * math.sqrt(most) + self.margin:
            active = True  # more than any noise gives: no need to look at single events
        else:
            supported = edi.background_activity_keep(events, self.width, self.height, self._last_t, self.support_us)
            self._s += int(np.count_nonzero(supported))
            self._tested += n
            active = self._s > self._noise_bound(self._tested, rate_hz)
        if active:
            self.last_active_us = t_end
        if active or t_end - self._w0 >= self.window_us:
            self.windows += 1
            self.active_windows += int(active)
            self._w0, self._n, self._s, self._tested = t_end, 0, 0, 0
        return active

    def _noise_bound(self, n: int, rate_hz: float) -> float:
        """The most supported events that n events of pure noise at rate_hz per pixel plausibly give."""
        p = 1.0 - math.exp(-8.0 * rate_hz * self.support_us * 1e-6)
        mean = n * p
        return mean + self.sigmas * math.sqrt(mean * (1.0 - p)) + self.margin

    def active_since(self, t_us: int | None) -> bool:
        """Whether a window judged active ended at or after t_us (None: ever)."""
        if self.last_active_us is None:
            return False
        return t_us is None or self.last_active_us >= t_us


class StaticScene:
    """The worker's static-scene state around SceneActivity: whether the scene was active since the latest
    deblurred APS frame, and per chunk whether its events are only noise, an onset, or part of activity that
    went on within `hold_us` (sensor time)."""

    def __init__(self, hold_us: int = 50_000) -> None:
        self.hold_us = hold_us
        self.activity: SceneActivity | None = None  # sized by the first APS frame
        self.active = False
        self.ref_end_us: int | None = None  # exposure end of the latest deblurred APS frame
        self.changed = True  # active between the previous deblurred frame and the current one
        self.noise_only_events = 0

    @property
    def quiet(self) -> bool:
        """The latest events showed only noise (False before the first APS frame: nothing is judged then)."""
        return self.activity is not None and not self.active

    def active_since_reference(self) -> bool:
        return self.activity is None or self.activity.active_since(self.ref_end_us)

    def new_reference(self, frame: Frame, anchor: bool = False) -> None:
        """An APS frame is deblurred: remember whether the scene changed since the previous one (`anchor`: it
        re-anchors the state after a gap, which counts as a change)."""
        self.changed = anchor or self.active_since_reference()
        self.ref_end_us = frame.exposure_end_us
        if self.activity is None:
            self.activity = SceneActivity(frame.image.shape[1], frame.image.shape[0])

    def observe(self, events: np.ndarray) -> str:
        """"noise" (no frame is due for these events), "onset" (active after noise) or "active"."""
        if self.activity is None:
            return "active"
        self.activity.update(events)
        active = self.activity.active_since(int(events["t"][-1]) - self.hold_us)
        onset = active and not self.active
        self.active = active
        if not active:
            self.noise_only_events += len(events)
            return "noise"
        return "onset" if onset else "active"
