"""c estimators: search helpers, recovery of the simulator's c, the cheap fit test, and degenerate input."""

from __future__ import annotations

import numpy as np
import pytest
from tests.edi_live.edi_scenes import make_scene

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE


def frame_data(scene, frame, *, segments=False, tau_frac=0.25):
    b, informative = edi.blurry_to_float(frame.image)
    table = edi.build_level_table(scene.events, scene.width, scene.height, frame.exposure_start_us,
                                  frame.exposure_end_us, segments=segments)
    m = contrast.event_map(scene.events, scene.width, scene.height, table.ref_t_us, frame.exposure_start_us,
                           frame.exposure_end_us, tau_frac * frame.exposure_us)
    return contrast.FrameData(b, informative, table, m)


def pairs_of(scene, *, segments=False):
    frames = [frame_data(scene, fr, segments=segments) for fr in scene.frames]
    pairs = []
    for prev, cur in zip(frames, frames[1:]):
        n_on, n_off = edi.signed_counts(scene.events, scene.width, scene.height, t0=prev.table.ref_t_us + 1,
                                        t1=cur.table.ref_t_us)
        pairs.append(contrast.FramePair(prev, cur, n_on, n_off))
    return frames, pairs


def test_golden_section_finds_the_minimum():
    x, fx, n = contrast.golden_section(lambda c: (c - 0.3137) ** 2, 0.01, 2.0, tol=1e-4)
    assert abs(x - 0.3137) < 1e-4 and n < 40


def test_grid_then_golden_escapes_a_local_minimum():
    fn = lambda c: min((c - 0.05) ** 2 + 0.01, 0.1 * (c - 0.8) ** 2)  # noqa: E731 - global minimum at 0.8
    x, _ = contrast.grid_then_golden(fn, 0.02, 2.0, n_grid=10, tol=1e-4)
    assert abs(x - 0.8) < 1e-3


SCENES = [  # texture, c, velocity px/ms
    ("brick", 0.15, (0.5, 0.2)),
    ("brick", 0.3, (1.0, -0.4)),
    ("camera", 0.2, (0.5, 0.2)),
    ("camera", 0.3, (1.0, -0.4)),
    ("gravel", 0.25, (0.8, 0.3)),
    ("grass", 0.3, (0.5, 0.2)),
]
# Known weak spot (reported in the README): fine texture at fast motion (grass at 1 px/ms, 8 px of blur) biases
# the estimate low by about 0.03.


@pytest.mark.parametrize("case", range(len(SCENES)))
def test_consistency_recovers_simulated_c(case):
    tex, c, velocity = SCENES[case]
    scene = make_scene(tex, c_on=c, velocity_px_per_ms=velocity, width=80, height=60, n_frames=4, sigma_c=0.02,
                       seed=case)
    _, pairs = pairs_of(scene)
    est = contrast.make_estimator("consistency")
    c_on, c_off = est.estimate(None, pairs, (0.2, 0.2))
    assert c_on == c_off
    assert abs(c_on - c) <= 0.03, f"{tex}: estimated {c_on:.3f}, simulated {c}"


def test_consistency_recovers_separate_thresholds():
    scene = make_scene("brick", c_on=0.3, c_off=0.2, width=80, height=60, n_frames=3, sigma_c=0.02)
    _, pairs = pairs_of(scene, segments=True)
    c_on, c_off = contrast.ConsistencyContrast(separate=True).estimate(None, pairs, (0.2, 0.2))
    assert abs(c_on - 0.3) <= 0.03 and abs(c_off - 0.2) <= 0.03


def test_fit_test_accepts_true_c_and_rejects_a_wrong_one():
    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=3)
    _, pairs = pairs_of(scene)
    est = contrast.ConsistencyContrast()
    assert est.misfit(None, pairs, (0.25, 0.25)) < est.fit_z
    assert est.misfit(None, pairs, (0.35, 0.35)) >= est.fit_z
    assert est.misfit(None, pairs, (0.18, 0.18)) >= est.fit_z


def test_consistency_says_nothing_without_pairs_or_events():
    est = contrast.ConsistencyContrast()
    assert est.estimate(None, [], (0.2, 0.2)) is None
    assert est.misfit(None, [], (0.2, 0.2)) is None
    img = np.full((20, 30), 100, np.uint8)
    b, informative = edi.blurry_to_float(img)
    empty = edi.build_level_table(np.zeros(0, EVENT_DTYPE), 30, 20, 0, 1000)
    fd = contrast.FrameData(b, informative, empty)
    zeros = np.zeros(600, np.int64)
    assert est.estimate(fd, [contrast.FramePair(fd, fd, zeros, zeros)], (0.2, 0.2)) is None


def test_energy_estimator_returns_a_c_in_its_range():
    scene = make_scene("camera", c_on=0.2, n_frames=1)
    fd = frame_data(scene, scene.frames[0])
    est = contrast.make_estimator("energy")
    c_on, c_off = est.estimate(fd, [], (0.2, 0.2))
    assert est.c_min <= c_on <= est.c_max and c_on == c_off


def test_fixed_and_unknown_estimators():
    fixed = contrast.FixedContrast(0.3, 0.2)
    assert fixed.estimate(None, [], (0.1, 0.1)) == (0.3, 0.2) and fixed.misfit(None, [], (0.3, 0.2)) is None
    with pytest.raises(ValueError, match="unknown c estimator"):
        contrast.make_estimator("psychic")


def test_per_pixel_terms_sum_to_the_cost_and_match_the_numpy_formula():
    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=3)
    _, pairs = pairs_of(scene, segments=True)  # segments: the numpy path can evaluate c_on != c_off
    cost = contrast.ConsistencyContrast()._problem(pairs[-1:])
    for c in (0.1, 0.25, 0.6):
        fast = cost.terms(c, c)  # the numba kernel when numba is there
        ref = cost.terms(c, c * (1 + 1e-12))  # always the numpy formula
        np.testing.assert_allclose(fast, ref, rtol=1e-6, atol=1e-9)
        assert cost(c, c) == pytest.approx(fast.sum(), rel=1e-9)


def test_fit_score_and_information_are_in_standard_errors():
    est = contrast.ConsistencyContrast()
    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=3)
    _, pairs = pairs_of(scene)
    assert est.fit_score(pairs, (0.25, 0.25)) < est.fit_z < est.fit_score(pairs, (0.35, 0.35))
    assert est.information(pairs, (0.25, 0.25)) >= est.info_z
    # the slower the motion, the fewer pixels pin c down: the information shrinks
    info = []
    for v in ((0.01, 0.0), (0.05, 0.02)):  # below ~50 px/s on this scene (faster: blur takes information away)
        slow = make_scene("camera", c_on=0.25, velocity_px_per_ms=v, width=80, height=60, n_frames=3, seed=1)
        _, pr = pairs_of(slow)
        info.append(est.information(pr, (0.25, 0.25)))
    assert info[0] < info[1]


def test_the_estimators_dot_product_is_the_plain_sum_of_products(rng):
    from edi_live.contrast.vectors import dot

    a, b = rng.normal(size=50_000), rng.normal(size=50_000)
    assert dot(a, b) == pytest.approx(float(np.sum(a * b)), rel=1e-9)
    assert dot(a[:0], b[:0]) == 0.0
