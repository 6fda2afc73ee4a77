"""When to (re-)estimate the APS black level from the stream, and what to make of an estimate.

The math is edi_live.contrast.black_level; this module owns the decision state only: the pool of quiet-pixel
samples of recent frame pairs, when an estimate is due, whether it carries information, and the short history
whose median is the black level. A given value (flag, TOML key) is never replaced; a starting value (a saved
calibration's) is in use until an estimate is kept, unless it lies above MAX_BLACK_DN, where the fit cannot reach:
then it is given.

Rules: every pair enters a pool of the last `pool_pairs` pairs, with its quiet pixels sampled only when an estimate
will read it (otherwise an empty placeholder, which leaves the pool before any estimate). At start-up an estimate is due
once the pool holds `min_pairs` pairs and `min_pixels` pixels (a single pair is too noisy: +-3 DN on the simulator),
and again on every `startup_step`-th pair after that until it is full; after that every `recheck_every` pairs.
An estimate is kept only when its cost beats the values 4 DN either side by `info_z` standard error(s) and dark
pixels support it (at least `min_support` moving quiet pixels, and `support_fraction` of them, have their darker
frame within black_level.SUPPORT_DN of it: without such pixels the profile's z measures the scene's texture, not
the black level; the ideal 'blocks' scene gave 9 DN at z 2.9 with 31 of 1916); it enters a history of `history`
estimates whose median is the black level (until the first kept estimate: `start`, e.g. a saved calibration's,
else 0 DN). An estimate of at most `zero_below_dn` enters as 0 DN: that is the
fit's systematic error on supported scenes (2-3 DN on the ideal astronaut scene, -1 to -2 on the camera scene with
10 DN), and 0 is what DV's 8-bit frames reach. An estimate above that is first corrected for the APS noise
(contrast/black_level_noise.py: the noise measured on neighbouring event-free pixels, then SIMEX), which pulls the
profile's minimum low (10 DN was found as 7 with 1 DN RMS noise); the pairs' noise samples are taken only while
the pool fills and in the `pool_pairs` pairs before a recheck.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from edi_live.contrast import FramePair
from edi_live.contrast.black_level import QuietSamples, fit_black_level, quiet_samples
from edi_live.contrast.black_level_noise import noise_corrected, samples_with_noise

MAX_BLACK_DN = 60.0  # estimates are searched on [0, this]; a larger offset is not a black level but a setting


@dataclass(frozen=True)
class BlackLevelSettings:
    pool_pairs: int = 12
    min_pairs: int = 2
    min_pixels: int = 300
    startup_step: int = 1  # until the pool is full, an estimate on every new pair after the first `min_pairs`
    recheck_every: int = 100  # once the pool is full; a fit costs ~15 ms at 240x180 and the black level is steady
    info_z: float = 2.5
    min_support: int = 50
    support_fraction: float = 0.05
    zero_below_dn: float = 3.0
    history: int = 3
    noise_correction: bool = True  # correct a kept estimate for the APS noise (contrast/black_level_noise.py)


class BlackLevelPolicy:
    """`update(pair, taken_off)` per new frame pair; returns the black level to use from now on when it changed."""

    def __init__(self, given: float | None, settings: BlackLevelSettings = BlackLevelSettings(), *,
                 start: float | None = None) -> None:
        if start is not None and not 0.0 <= float(start) < 128.0:
            raise ValueError(f"a starting black level must be in [0, 128) DN (got {start!r})")
        if given is None and start is not None and float(start) > MAX_BLACK_DN:
            given = float(start)  # beyond the fit's range: it could only replace it with the range's edge
        self.given = given
        self.settings = settings
        self.value = float(given if given is not None else (start or 0.0))
        self.from_calibration = given is None and start is not None  # the start is in use, no estimate kept yet
        self.estimates = 0
        self.last_fit: dict = {}
        self._pool: collections.deque = collections.deque(maxlen=max(1, settings.pool_pairs))
        self._since = 0
        self._startup_marks = self._startup_schedule()
        self._history: collections.deque = collections.deque(maxlen=max(1, settings.history))

    @property
    def estimated(self) -> bool:
        return self.given is None

    def samples(self) -> bool:
        """Whether the next update reads its pair's frames (their level tables among them); may say yes when it
        will not (after an estimate the count restarts), never no when it will."""
        if self.given is not None:
            return False
        return bool(self._startup_marks) or self._soon()

    def _soon(self) -> bool:
        # only the pairs the next estimate will pool are sampled (the noise sample alone costs a few ms a pair):
        # after start-up, a pair more than `pool_pairs` before the recheck leaves the pool before it is read
        return (len(self._pool) < self._pool.maxlen
                or self._since >= self.settings.recheck_every - self._pool.maxlen)

    def update(self, pair: FramePair | None, taken_off: float) -> float | None:
        if self.given is not None or pair is None:
            return None
        soon = self._soon()
        if not soon and not self._startup_marks:  # (a start-up estimate put off for too few pixels reads them all)
            self._pool.append(None)
        elif self.settings.noise_correction and soon:
            self._pool.append(samples_with_noise(pair, taken_off))
        else:
            self._pool.append(quiet_samples(pair, taken_off))
        self._since += 1
        startup = due = bool(self._startup_marks and len(self._pool) >= self._startup_marks[0])
        if due:
            self._startup_marks.pop(0)
        elif not self._startup_marks and self._since >= self.settings.recheck_every:
            due = True
        if not due:
            return None
        samples = QuietSamples.join([p for p in self._pool if p is not None])
        if samples.size < self.settings.min_pixels:
            if not self._startup_marks:
                self._startup_marks = [len(self._pool)]  # try again on the next pair
            return None
        self._since = 0
        fit = fit_black_level(samples, (0.0, MAX_BLACK_DN))
        if fit is None:
            return None
        self.estimates += 1
        self.last_fit = {"black_level": fit.black_level, "z": round(fit.z, 2), "pixels": fit.pixels,
                         "support": fit.support, "moving": fit.moving}
        if not fit.z >= self.settings.info_z:
            self.last_fit["decision"] = "flat"
            return None
        if fit.support < max(self.settings.min_support, self.settings.support_fraction * fit.moving):
            self.last_fit["decision"] = "no dark pixels"
            return None
        if startup:  # a start-up estimate saw more pairs than the one before: it supersedes it
            self._history.clear()
        value = fit.black_level
        if self.settings.noise_correction and value > self.settings.zero_below_dn:
            corrected, sigma = noise_corrected(samples, fit.black_level)
            value = float(min(max(round(corrected), 0.0), MAX_BLACK_DN))
            self.last_fit.update(corrected=value, noise_dn=None if sigma is None else round(sigma, 2))
        self._history.append(value if value > self.settings.zero_below_dn else 0.0)
        new = float(np.median(self._history))
        self.last_fit["decision"] = "update"
        self.from_calibration = False
        if new == self.value:
            return None
        self.value = new
        return new

    def _startup_schedule(self) -> list[int]:
        s = self.settings
        marks = list(range(max(1, s.min_pairs), max(1, s.pool_pairs) + 1, max(1, s.startup_step)))
        return marks or [1]
