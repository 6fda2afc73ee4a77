"""ContrastPolicy on its own: a scripted estimator stands in for the math, so each rule of the policy (start-up,
fit-test patience, still-scene verdict and its confirmation, flat estimates, the median history) is checked
against what the rule says, frame by frame."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from edi_live.c_policy import ContrastPolicy, PolicySettings

PAIR = object()  # the policy only counts pairs and hands them on


@dataclass
class Scripted:
    """Answers from queues; records how often each question was asked."""

    estimates: list = field(default_factory=list)
    misfits: list = field(default_factory=list)
    info: float | None = 10.0
    confirm: float | None = None
    name: str = "scripted"
    needs_pair: bool = True
    separate: bool = False
    needs_full_image: bool = False
    c_min: float = 0.02
    fit_z: float = 3.0
    info_z: float = 2.0
    asked: dict = field(default_factory=lambda: {"estimate": 0, "misfit": 0, "still": 0, "confirm": 0})

    def estimate(self, cur, pairs, c_init):
        self.asked["estimate"] += 1
        return self.estimates.pop(0)

    def misfit(self, cur, pairs, c):
        self.asked["misfit"] += 1
        return self.misfits.pop(0) if self.misfits else 0.0

    def still_misfit(self, cur, pairs, floor, cached):
        self.asked["still"] += 1
        return self.misfits.pop(0) if self.misfits else 0.0

    def confirm_still(self, pairs, c, floor):
        self.asked["confirm"] += 1
        return self.confirm

    def information(self, pairs, c):
        return self.info


def run(policy, frames, pairs=2):
    for _ in range(frames):
        policy.update(None, [PAIR] * pairs)


def test_waits_for_a_pair_then_estimates_at_start_up_until_the_history_is_full():
    est = Scripted(estimates=[(0.3, 0.3), (0.32, 0.32)])
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=2))
    policy.update(None, [])
    assert est.asked["estimate"] == 0 and policy.c == (0.2, 0.2)
    policy.update(None, [PAIR])  # first estimate
    assert policy.c == (0.3, 0.3)
    policy.update(None, [PAIR, PAIR])  # the start-up estimate on the full history supersedes the first
    assert policy.c == (0.32, 0.32) and policy.reestimations == 2
    run(policy, 3)
    assert est.asked["estimate"] == 2, "after start-up the cached c holds while the fit test passes"


def test_a_failing_fit_test_needs_patience_unless_it_fails_strongly():
    est = Scripted(estimates=[(0.3, 0.3), (0.3, 0.3), (0.4, 0.4), (0.5, 0.5)],
                   misfits=[3.5, 0.0, 3.5, 3.5, 9.5])
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1, fit_patience=2, fit_strong=3.0))
    run(policy, 1)  # first estimate
    run(policy, 1)  # fails once: not yet
    run(policy, 1)  # passes: the count restarts
    run(policy, 1)  # fails once
    assert policy.reestimations == 1
    run(policy, 1)  # fails twice in a row: re-estimate
    assert policy.reestimations == 2 and policy.last_fit["decision"] == "update"
    run(policy, 1)  # 9.5 >= 3 x fit_z: at once
    assert policy.reestimations == 3
    assert policy.c == (0.3, 0.3), "c is the median of the last estimates (0.3, 0.3, 0.4)"


def test_reestimate_every_k_frames():
    est = Scripted(estimates=[(0.3, 0.3)] * 10)
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1, reestimate_every=3))
    run(policy, 7)
    assert est.asked["estimate"] == 3  # frames 1, 4, 7


def test_a_still_verdict_is_believed_at_start_up_and_confirmed_later():
    floor = 0.02
    est = Scripted(estimates=[(floor, floor)])
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1))
    run(policy, 1)
    assert policy.events_ignored and policy.last_fit["decision"] == "still"

    est = Scripted(estimates=[(0.3, 0.3), (floor, floor)], misfits=[9.9], confirm=1.0)
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1))
    run(policy, 2)  # estimate, then a strong misfit finds the floor: only a vote
    assert not policy.events_ignored and policy.last_fit["decision"] == "still?"
    run(policy, 1)  # the next pair does not confirm it (z 1.0 < fit_z)
    assert not policy.events_ignored and est.asked["confirm"] == 1
    assert policy.c == (0.3, 0.3)


def test_a_confirmed_still_verdict_ignores_events_until_they_explain_changes_again():
    floor = 0.02
    est = Scripted(estimates=[(0.3, 0.3), (floor, floor), (0.35, 0.35)], misfits=[9.9, 0.0, 9.9], confirm=5.0)
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1))
    run(policy, 3)
    assert policy.events_ignored
    run(policy, 1)  # still_misfit 0.0: the floor still fits
    assert policy.events_ignored and est.asked["still"] == 1
    run(policy, 1)  # the cached c explains the frames clearly better than none: re-estimate, events count again
    assert not policy.events_ignored
    assert policy.c == pytest.approx((0.325, 0.325)), "the median of the accepted estimates 0.3 and 0.35"


def test_an_estimate_without_information_keeps_c():
    est = Scripted(estimates=[(0.9, 0.9)], info=0.5)
    policy = ContrastPolicy(est, 0.2, 0.2)
    run(policy, 1)
    assert policy.c == (0.2, 0.2) and policy.ill_conditioned == 1 and policy.last_fit["decision"] == "flat"


def test_estimates_are_clipped_to_the_threshold_range_and_z_values_stay_finite_or_nan():
    est = Scripted(estimates=[(9.0, 9.0)], misfits=[None])
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1))
    run(policy, 2)
    assert policy.c == (2.0, 2.0)
    assert math.isnan(policy.last_fit["fit_z"])


def test_an_estimator_that_needs_no_pair_believes_a_still_verdict_at_once():
    floor = 0.03
    est = Scripted(estimates=[(0.3, 0.3), (floor, floor)], misfits=[math.inf], needs_pair=False, c_min=floor)
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1))
    policy.update(None, [])
    policy.update(None, [])
    assert policy.events_ignored and est.asked["confirm"] == 0


def test_a_restart_estimates_afresh_and_forgets_the_history():
    # after the frames' black level changed, estimates made on the old frames must not hold c through the median
    est = Scripted(estimates=[(0.2, 0.2), (0.2, 0.2), (0.2, 0.2), (0.3, 0.3)])
    policy = ContrastPolicy(est, 0.25, 0.25, PolicySettings(startup_estimates=1, c_history=3))
    run(policy, 3)  # one estimate, then the fit test keeps it
    assert policy.c == (0.2, 0.2) and est.asked["estimate"] == 1
    policy.restart()
    run(policy, 1)
    assert est.asked["estimate"] == 2  # estimated at once, without a failed fit test
    policy.restart()
    est.estimates = [(0.3, 0.3)]
    run(policy, 1)
    assert policy.c == (0.3, 0.3)  # not the median with the 0.2 of before the restart


def test_settled_only_after_start_up_and_while_no_failure_or_still_vote_is_pending():
    est = Scripted(estimates=[(0.3, 0.3), (0.3, 0.3)], misfits=[0.0, 3.5, 0.0])
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=2))
    assert not policy.settled, "nothing estimated yet"
    run(policy, 1)
    assert not policy.settled, "one start-up estimate still to come"
    run(policy, 1)
    run(policy, 1)  # the fit test passes
    assert policy.settled
    run(policy, 1)  # fails once: the second test is pending
    assert not policy.settled
    run(policy, 1)  # passes again
    assert policy.settled and policy.reestimations == 2


def test_a_skipped_frame_counts_toward_reestimate_every_and_asks_nothing():
    est = Scripted(estimates=[(0.3, 0.3)] * 3)
    policy = ContrastPolicy(est, 0.2, 0.2, PolicySettings(startup_estimates=1, reestimate_every=3))
    run(policy, 1)
    policy.skip()
    policy.skip()
    assert est.asked == {"estimate": 1, "misfit": 0, "still": 0, "confirm": 0}
    run(policy, 1)  # the third frame since the estimate: due
    assert est.asked["estimate"] == 2
