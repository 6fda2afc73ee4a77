"""When to re-estimate c, and what to make of an estimate: the caching policy around a ContrastEstimator.

Owns the decision state only (is c estimated yet, start-up estimates left, consecutive fit-test failures, the
"still scene" verdict and its pending confirmation, the short history whose median is c). The math is the
estimator's (edi_live.contrast); the frames and pairs come from the reconstructor. No clocks, I/O or threads.

Rules, per APS frame once the estimator has what it needs (a pair for pairwise estimators):
- Estimate when due: the first frame, the start-up frames until the pair history is full, every
  `reestimate_every` frames if set, or when the fit test fails clearly: the cached c is beaten by a neighbour by
  `fit_z` standard errors on `fit_patience` consecutive frames, or by `fit_strong` x fit_z once.
- An estimate at the bottom of the search range means the events explain nothing (noise on a still scene): events
  are then ignored. Believed at once at start-up (or from estimators that cannot confirm it); later the next
  frame's pair must agree, since a pair across a scene cut looks the same.
- An estimate whose cost curve is flat (information below `info_z`) is no information: c stays.
- An accepted estimate enters a short history and c becomes its median, so one odd pair does not move c.
- Joint c (`joint_pairs` K > 0): estimates and fit tests pool the last K pairs (edi_live.contrast.joint), with the
  pairs that no c near the others' explains (a scene cut, a loop seam) set aside; two newest pairs that both
  disagree fail the fit test at once (the threshold changed). While every estimate so far was flat, c is estimated
  again each time the window holds one more pair.
- Which frames get a fit test at all is edi_live.calibration_schedule's: every frame until c has settled (`settled`),
  then every `settled_check_every`-th; a left-out frame only counts toward `reestimate_every` (`skip`).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from edi_live.contrast import ContrastEstimator, FrameData, FramePair, joint

C_RANGE = (0.01, 2.0)


@dataclass(frozen=True)
class PolicySettings:
    reestimate_every: int = 0  # 0: only when the fit test fails
    startup_estimates: int = 2  # estimates while the pair history fills (= history pairs)
    fit_patience: int = 2
    fit_strong: float = 3.0
    c_history: int = 3
    joint_pairs: int = 0  # K > 0: pool the last K pairs (the tracker must keep them)
    outlier_z: float = 6.0  # joint c: a pair whose own misfit at c reaches this is set aside


class ContrastPolicy:
    """Decides per frame whether to keep c or re-estimate it, and applies the result (c_on, c_off,
    events_ignored). `last_fit` records the frame's z values and decision, for tools and stats."""

    def __init__(self, estimator: ContrastEstimator, c_on: float, c_off: float,
                 settings: PolicySettings = PolicySettings()) -> None:
        self.estimator = estimator
        self.settings = settings
        self.c_on, self.c_off = float(c_on), float(c_off)
        self.reestimations = 0
        self.ill_conditioned = 0  # estimates that were no information (flat cost curve): c kept
        self.events_ignored = False  # the estimator found that the events carry no signal
        self.last_fit: dict = {}
        self._estimated = False
        self._frames_since_estimate = 0
        self._fit_fails = 0
        self._startup_left = max(1, settings.startup_estimates) - 1
        self._still_votes = 0
        self._history: collections.deque = collections.deque(maxlen=max(1, int(settings.c_history)))
        self._joint = int(settings.joint_pairs) if estimator.needs_pair else 0
        self._tried_with = 0  # joint c: pairs in the window at the last estimate

    @property
    def c(self) -> tuple[float, float]:
        return self.c_on, self.c_off

    @property
    def estimated(self) -> bool:
        """Whether c comes from an estimate (since the start or the last restart), not from the initial value."""
        return self._estimated

    @property
    def pools_pairs(self) -> bool:
        """Joint c: estimates and fit tests read the last K pairs."""
        return bool(self._joint)

    @property
    def settled(self) -> bool:
        """Estimated, past start-up, and nothing pending: no failed fit test waiting for its second, no still verdict
        waiting for its confirmation (edi_live.calibration_schedule thins the fit tests only then)."""
        return (self._estimated and self._startup_left <= 0 and not self._fit_fails and not self._still_votes
                and not (self._joint and not self._history))

    def skip(self) -> None:
        """A frame whose fit test the schedule left out: it counts toward `reestimate_every` and nothing else."""
        self._frames_since_estimate += 1
        self.last_fit = {}

    def restart(self) -> None:
        """The frames' calibration changed (e.g. the black level): estimate c afresh, forgetting the history."""
        self._estimated = False
        self._startup_left = max(1, self.settings.startup_estimates) - 1
        self._history.clear()
        self._still_votes = 0
        self._fit_fails = 0

    def update(self, cur: FrameData, pairs: Sequence[FramePair]) -> None:
        """One APS frame: `cur` is its data, `pairs` the recent consecutive-frame pairs (newest last)."""
        est = self.estimator
        if est.needs_pair and not pairs:
            return
        if self._joint:
            pairs = list(pairs)[-self._joint:]
        self.last_fit = info = {}
        self._frames_since_estimate += 1
        startup = self._estimated and self._startup_left > 0 and len(pairs) >= 2
        if startup:
            self._startup_left -= 1
        first = not self._estimated
        floor = (est.c_min, est.c_min)
        if self._still_votes:  # a still verdict after start-up waits for the next frame's pair
            self._still_votes = 0
            z = est.confirm_still(pairs[-1:], self.c, floor)
            info["still_z"] = _z(z)
            if z is not None and z >= est.fit_z:
                self.events_ignored = True
                info["decision"] = "still"
            return
        due = first or startup or bool(self.settings.reestimate_every
                                       and self._frames_since_estimate >= self.settings.reestimate_every)
        if self._joint and not self._history and len(pairs) > self._tried_with:
            due = True  # no informative estimate yet: the pooled window has grown
        if not due:
            due = self._fit_test_fails(cur, pairs if self._joint else pairs[-1:], floor, info)
        if due:
            self._estimate(cur, pairs, first, startup, floor, info)

    def _fit_test_fails(self, cur: FrameData, last: Sequence[FramePair], floor: tuple[float, float],
                        info: dict) -> bool:
        est = self.estimator
        if self.events_ignored:  # do the events now explain more at the cached c than at none?
            z = est.still_misfit(cur, last[-1:], floor, self.c)
        elif self._joint:
            verdict = joint.judge_pairs(est, cur, last, self.c, outlier_z=self.settings.outlier_z,
                                        run=self.settings.fit_patience)
            info["set_aside"] = verdict.set_aside
            if verdict.newest_disagree:
                info["fit_z"] = _z(verdict.pair_z[-1])
                return True
            z = est.misfit(cur, verdict.inliers, self.c)
        else:
            z = est.misfit(cur, last, self.c)
        fail = z is not None and z >= est.fit_z
        self._fit_fails = self._fit_fails + 1 if fail else 0
        info["fit_z"] = _z(z)
        return fail and (self._fit_fails >= self.settings.fit_patience or z >= self.settings.fit_strong * est.fit_z)

    def _estimate(self, cur: FrameData, pairs: Sequence[FramePair], first: bool, startup: bool,
                  floor: tuple[float, float], info: dict) -> None:
        est = self.estimator
        if self._joint:
            self._tried_with = len(pairs)
            found, pairs = joint.joint_estimate(est, cur, pairs, self.c, outlier_z=self.settings.outlier_z,
                                                run=self.settings.fit_patience)
        else:
            found = est.estimate(cur, pairs, self.c)
        if found is None:
            return
        info["found"] = float(found[0])
        self._estimated = True
        self.reestimations += 1
        self._frames_since_estimate = 0
        self._fit_fails = 0
        if floor[0] > 0 and max(found) <= 1.25 * floor[0]:
            if first or self.events_ignored or not est.needs_pair:
                self.events_ignored = True
                info["decision"] = "still"
            else:
                self._still_votes = 1
                info["decision"] = "still?"
            return
        z_info = est.information(pairs, found)
        info["info_z"] = _z(z_info)
        if z_info is not None and z_info < est.info_z:
            info["decision"] = "flat"  # keep the cached c (and whether events are applied)
            self.ill_conditioned += 1
            return
        self.events_ignored = False
        if startup:  # this estimate saw more pairs than the first one: it supersedes it
            self._history.clear()
        self._history.append(tuple(min(max(v, C_RANGE[0]), C_RANGE[1]) for v in found))
        self.c_on, self.c_off = (float(np.median(v)) for v in zip(*self._history))
        info["decision"] = "update"


def _z(z: float | None) -> float:
    return float("nan") if z is None else float(z)
