"""Joint c over the last K consecutive-frame pairs: one cost pooled over the pairs that agree, with the pairs that
do not (a scene cut such as a recording's loop seam, a burst of noise, a frame pair across unreported lost data)
set aside first. Pure functions over a ContrastEstimator's pairwise evaluations; when to use them is the c
policy's business (edi_live.c_policy).

Why pooling: one pair sees a few hundred moving pixels, so its cost curve can be too flat to say anything (the
estimate is then rejected as "flat") and consecutive estimates scatter; K pairs see K times the pixels. Why the
set-aside: the pooled cost of a consistency estimator is a sum over pixels, so one pair that no c explains pulls
the pooled minimum towards the floor ("the events explain nothing") in proportion to its pixels.

A pair is an outlier at c when its own misfit z (est.misfit on that pair alone: how many standard errors a
neighbour of c explains it better) reaches `outlier_z`. Only a minority is set aside (the worst ones): when most
pairs disagree with c, c is what is wrong, not the pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from edi_live.contrast.frames import ContrastEstimator, FrameData, FramePair


@dataclass(frozen=True)
class PairVerdict:
    """The pairs that agree with c (oldest first), how many were set aside, each pair's misfit z (None: the pair
    says nothing), and whether the newest `run` pairs all disagree (a change of c rather than an odd pair)."""

    inliers: list[FramePair]
    set_aside: int
    pair_z: list[float | None]
    newest_disagree: bool


def judge_pairs(est: ContrastEstimator, cur: FrameData, pairs: Sequence[FramePair], c: tuple[float, float], *,
                outlier_z: float, run: int = 2) -> PairVerdict:
    """Each pair's misfit at c; the worst pairs at or above outlier_z are set aside while they are a minority."""
    zs = [est.misfit(cur, [p], c) for p in pairs]
    bad = sorted((i for i, z in enumerate(zs) if z is not None and z >= outlier_z), key=lambda i: -zs[i])
    limit = (len(pairs) - 1) // 2
    drop = set(bad[:limit]) if len(bad) <= limit else set()
    newest = zs[-run:] if run > 0 else []
    disagree = len(pairs) >= run and all(z is not None and z >= outlier_z for z in newest)
    return PairVerdict([p for i, p in enumerate(pairs) if i not in drop], len(drop), zs, disagree)


def joint_estimate(est: ContrastEstimator, cur: FrameData, pairs: Sequence[FramePair], c: tuple[float, float], *,
                   outlier_z: float, run: int = 2) -> tuple[tuple[float, float] | None, list[FramePair]]:
    """(c from the pooled cost of the agreeing pairs, those pairs). When the newest `run` pairs all disagree with
    c, only the newest run of disagreeing pairs is used (the threshold changed: older pairs describe the old c).
    The set-aside is judged again at the new estimate once: at a stale c (the start value) every pair may disagree,
    so that nothing was set aside, and a pair rejected at a stale c can return."""
    verdict = judge_pairs(est, cur, pairs, c, outlier_z=outlier_z, run=run)
    pool = list(pairs)
    if verdict.newest_disagree:
        k = 0
        for z in reversed(verdict.pair_z):
            if z is None or z < outlier_z:
                break
            k += 1
        pool = pool[-k:]
    use = pool if verdict.newest_disagree else verdict.inliers
    found = est.estimate(cur, use, c)
    if found is None:
        return None, use
    again = judge_pairs(est, cur, pool, found, outlier_z=outlier_z, run=run).inliers
    if len(again) != len(use) or any(a is not b for a, b in zip(again, use)):
        refit = est.estimate(cur, again, found)
        if refit is not None:
            return refit, again
    return found, use
