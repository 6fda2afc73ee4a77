"""The APS black level estimated from events and frames (edi_live.contrast.black_level, black_level_policy), on
scenes built here with the simulator's camera model: recovered within 2 DN, and ~0 on an ideal camera."""

from __future__ import annotations

import numpy as np
import pytest
from tests.edi_live.edi_scenes import make_scene

from edi_live.black_level_policy import BlackLevelPolicy
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import preset, simulate, with_effects


def _between(ev: np.ndarray, t0: int, t1: int, left: bool) -> np.ndarray:
    t = ev["t"]
    return ev[np.searchsorted(t, t0, "left" if left else "right"):np.searchsorted(t, t1, "left")]


def _run(sim, rec: EdiReconstructor) -> EdiReconstructor:
    frames = sim.frames
    for k, f in enumerate(frames):
        rec.on_frame(f, _between(sim.events, f.exposure_start_us, f.exposure_end_us + 1, True))
        if k + 1 < len(frames):
            rec.on_events(_between(sim.events, f.exposure_end_us, frames[k + 1].exposure_start_us, False))
    return rec


@pytest.fixture(scope="module")
def camera_scene():
    return preset("translate", texture="camera", velocity_px_s=(200.0, 50.0), duration_s=0.5, seed=21,
                  ground_truth=False)


def test_a_black_level_is_recovered_within_2_dn(camera_scene):
    cfg = with_effects(camera_scene, "black_level")  # 10 DN
    sim = simulate(cfg)
    rec = _run(sim, EdiReconstructor(cfg.width, cfg.height, black_level=None))
    assert abs(rec.black_level - cfg.aps_offset_dn) <= 2.0, rec.stats()
    assert rec.stats()["black_level_estimated"]


def test_an_ideal_camera_keeps_a_black_level_near_zero(camera_scene):
    sim = simulate(camera_scene)
    rec = _run(sim, EdiReconstructor(camera_scene.width, camera_scene.height, black_level=None))
    assert rec.black_level <= 2.0


def test_an_ideal_small_scene_with_short_exposures_keeps_zero():
    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=8, sigma_c=0.02, seed=3)
    rec = _run(scene, EdiReconstructor(scene.width, scene.height, black_level=None))
    assert rec.black_level <= 2.0


def test_a_given_black_level_always_wins(camera_scene):
    cfg = with_effects(camera_scene, "black_level")
    sim = simulate(cfg)
    rec = _run(sim, EdiReconstructor(cfg.width, cfg.height, black_level=3.0))
    assert rec.black_level == 3.0 and not rec.stats()["black_level_estimated"]
    assert BlackLevelPolicy(3.0).update(None, 0.0) is None


def test_a_fixed_c_does_not_estimate_the_black_level(camera_scene):
    rec = EdiReconstructor(camera_scene.width, camera_scene.height, c=0.2, black_level=None)
    assert rec.black_level == 0.0 and not rec.stats()["black_level_estimated"]
