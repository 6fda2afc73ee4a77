"""Joint c over several frame pairs (edi_live.contrast.joint): steadier than one pair on a generated scene, robust
to a pair across a scene cut, and the policy's use of it (a looped stream re-estimates less)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tests.edi_live.edi_scenes import make_scene
from tests.edi_live.test_contrast import pairs_of

import edi_live.contrast as contrast
from edi_live.contrast import joint
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate

K = 6


def _noisy_scene(seed: int, n_frames: int = 12):
    return make_scene("brick", c_on=0.25, width=80, height=60, n_frames=n_frames, sigma_c=0.05, noise_hz=0.5,
                      velocity_px_per_ms=(0.3, 0.1), seed=seed)


def test_joint_c_recovers_c_with_less_spread_than_one_pair():
    est = contrast.make_estimator("consistency")
    single, pooled = [], []
    for seed in (1, 2):
        _, pairs = pairs_of(_noisy_scene(seed))
        for k in range(K - 1, len(pairs)):
            single.append(est.estimate(None, [pairs[k]], (0.2, 0.2))[0])
            pooled.append(joint.joint_estimate(est, None, pairs[k - K + 1:k + 1], (0.2, 0.2), outlier_z=6.0)[0][0])
    single, pooled = np.array(single), np.array(pooled)
    assert np.std(pooled) < 0.7 * np.std(single), (np.std(pooled), np.std(single))
    assert np.mean(np.abs(pooled - 0.25)) <= np.mean(np.abs(single - 0.25)) + 0.005


def test_a_pair_across_a_scene_cut_is_set_aside():
    est = contrast.make_estimator("consistency")
    _, pairs = pairs_of(_noisy_scene(1, n_frames=K + 1))
    _, other = pairs_of(make_scene("camera", c_on=0.25, width=80, height=60, n_frames=3, seed=9))
    cut = contrast.FramePair(pairs[2].prev, other[0].cur, pairs[2].n_on, pairs[2].n_off)  # frames of two scenes
    window = pairs[:2] + [cut] + pairs[3:]
    clean = est.estimate(None, pairs[:2] + pairs[3:], (0.2, 0.2))[0]
    verdict = joint.judge_pairs(est, None, window, (clean, clean), outlier_z=6.0)
    assert verdict.set_aside == 1 and all(p is not cut for p in verdict.inliers)
    found, used = joint.joint_estimate(est, None, window, (0.2, 0.2), outlier_z=6.0)
    plain = est.estimate(None, window, (0.2, 0.2))[0]
    assert all(p is not cut for p in used) and abs(found[0] - clean) < 0.01
    assert abs(found[0] - clean) <= abs(plain - clean)


@dataclass
class _ByPair:
    """A stand-in estimator whose misfit is a property of each pair (its `z`)."""

    name: str = "by-pair"
    needs_pair: bool = True

    def misfit(self, cur, pairs, c):
        return max(p.z for p in pairs)


@dataclass
class _P:
    z: float


def test_only_a_minority_is_set_aside_and_two_newest_disagreeing_pairs_mean_a_change():
    est = _ByPair()
    one = joint.judge_pairs(est, None, [_P(0), _P(9), _P(0), _P(0)], (0.2, 0.2), outlier_z=6.0)
    assert one.set_aside == 1 and not one.newest_disagree
    most = joint.judge_pairs(est, None, [_P(9), _P(9), _P(0), _P(9)], (0.2, 0.2), outlier_z=6.0)
    assert most.set_aside == 0 and len(most.inliers) == 4  # c is what is wrong, not the pairs
    change = joint.judge_pairs(est, None, [_P(0), _P(0), _P(0), _P(0), _P(9), _P(9)], (0.2, 0.2), outlier_z=6.0)
    assert change.newest_disagree


def _looped(passes: int):
    sim = simulate(SceneConfig(width=96, height=72, duration_s=0.3, texture="blocks", velocity_px_s=(150.0, 30.0),
                               c_on=0.25, c_off=0.25, c_sigma=0.03, noise_rate_hz=0.2, seed=4))
    span = int(sim.events["t"][-1]) - int(sim.events["t"][0]) + 1
    for k in range(passes):
        for f in sim.frames:
            i0, i1 = np.searchsorted(sim.events["t"], [f.exposure_start_us, f.exposure_end_us + 1])
            ev = sim.events[i0:i1].copy()
            ev["t"] += k * span
            yield (f.__class__(f.image, f.exposure_start_us + k * span, f.exposure_end_us + k * span), ev)


def test_a_looped_stream_re_estimates_less_with_joint_c():
    """Each loop seam is a pair across a scene cut: one pair's fit test fails there and c jumps; the pooled window
    sets the seam aside (the same scene comes back, so c should not move)."""
    counts, spread = {}, {}
    for k in (0, K):
        rec = EdiReconstructor(96, 72, joint_pairs=k, separate_thresholds=False)
        cs = []
        for frame, ev in _looped(3):
            rec.on_frame(frame, ev)
            cs.append(rec.c_on)
        counts[k] = rec.reestimations
        spread[k] = float(np.std(cs[3:]) / np.median(cs[3:]))
    assert counts[K] < counts[0], counts
    assert spread[K] < spread[0], spread


def test_the_node_estimates_c_jointly_in_fused_mode_only():
    from edi_live.config import EdiConfig
    from edi_live.fused_mode import JOINT_PAIRS
    from edi_live.node import default_reconstructor

    assert default_reconstructor(8, 6, EdiConfig(mode="fused")).settings.joint_pairs == JOINT_PAIRS > 1
    assert default_reconstructor(8, 6, EdiConfig(mode="causal")).settings.joint_pairs == 0
