"""The schedule of the steady-state calibration checks (calibration_schedule, used by frame_calibration): every
frame while the calibration is young or changed, thinned once it settled, and a threshold that changes mid-stream
still re-estimated within a few frames (a simulated scene whose c jumps, against the simulator's true c)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from edi_live.calibration_schedule import CalibrationSchedule, ScheduleSettings
from edi_live.errors import ConfigError
from edi_live.reconstructor import EdiReconstructor
from tests.edi_live.edi_scenes import make_scene
from tests.edi_live.test_reconstructor import stream


def _plans(schedule, calm_flags):
    out = []
    for calm in calm_flags:
        out.append(schedule.plan())
        schedule.observe(calm, changed=not calm)
    return out


def test_every_frame_until_the_calibration_has_been_calm_for_a_while_then_one_test_in_c_every():
    s = CalibrationSchedule(ScheduleSettings(calm_frames=3, c_every=4))
    plans = _plans(s, [True] * 15)
    tested = [k for k, p in enumerate(plans) if p.c_test]
    assert tested == [0, 1, 2, 6, 10, 14]
    assert [s.plan() for _ in range(3)] == [s.plan()] * 3, "asking again before observe() changes nothing"


def test_a_change_brings_back_every_frame_for_calm_frames_and_a_lone_failure_for_one_frame():
    settings = ScheduleSettings(calm_frames=3, c_every=4)
    s = CalibrationSchedule(settings)
    _plans(s, [True] * 5)
    assert s.thinned
    s.observe(False, changed=True)  # e.g. c re-estimated
    assert [p.c_test for p in _plans(s, [True] * 4)] == [True, True, True, False]
    s.observe(False, changed=False)  # a fit test failed once; c kept so far
    assert s.plan().c_test, "the failure's second test comes on the next frame"
    s.observe(True, changed=False)  # it passed: thinned again at once
    assert s.thinned


def test_c_every_1_never_thins_and_bad_settings_are_refused():
    s = CalibrationSchedule(ScheduleSettings(c_every=1, calm_frames=0))
    assert all(p.c_test for p in _plans(s, [True] * 10))
    with pytest.raises(ValueError):
        CalibrationSchedule(ScheduleSettings(c_every=0))
    with pytest.raises(ConfigError):
        EdiReconstructor(16, 12, settled_check_every=0)


# ---- on a simulated stream ----

C_BEFORE, C_AFTER = 0.22, 0.34
N_FRAMES = 34
CHANGES = (21, 22, 23, 24)  # the threshold changes between frames k - 1 and k: every phase of the thinned tests
CHECK_EVERY = 4
# frames after the change until c is re-estimated: the next thinned test (at most CHECK_EVERY - 1 frames after the
# change's frame) fails, the fit test's second failure comes on the frame after it
MAX_DELAY = CHECK_EVERY + 1


@pytest.fixture(scope="module")
def two_thresholds():
    """One moving scene simulated with the thresholds before and after the jump (the APS frames are the same:
    they do not depend on c)."""
    kw = dict(width=80, height=60, n_frames=N_FRAMES, sigma_c=0.02, seed=11, velocity_px_per_ms=(0.3, 0.12))
    return make_scene("brick", c_on=C_BEFORE, **kw), make_scene("brick", c_on=C_AFTER, **kw)


def _jump(scenes, change_at):
    """The events before the jump from the first scene, after it from the second, as when the camera's bias
    changes between two frames."""
    a, b = scenes
    t_jump = (a.frames[change_at - 1].exposure_end_us + a.frames[change_at].exposure_start_us) // 2
    events = np.concatenate([a.events[a.events["t"] < t_jump], b.events[b.events["t"] >= t_jump]])
    return dataclasses.replace(a, events=events, c_on=C_AFTER, c_off=C_AFTER)


def _run(scene, every):
    """(per frame: its fit test planned, the checks thinned, the c decided in its settle)."""
    rec = EdiReconstructor(scene.width, scene.height, c_init=0.2, settled_check_every=every)
    tested, thinned, decided = [], [], []
    for k, frame in enumerate(scene.frames):  # one frame at a time, to look at the schedule in between
        schedule = rec._calib.schedule
        thinned.append(schedule.thinned)
        tested.append(schedule.plan().c_test)
        stream(dataclasses.replace(scene, frames=[frame], events=scene.events[_event_range(scene, k)]), rec)
        decided.append(rec._policy.c[0])
    return tested, thinned, decided


def _event_range(scene, k):
    t = scene.events["t"]
    lo = int(np.searchsorted(t, scene.frames[k - 1].exposure_end_us, side="right")) if k else 0
    hi = int(np.searchsorted(t, scene.frames[k].exposure_end_us, side="right"))
    return slice(lo, hi)


def _delay(decided, change_at):
    """Frames from the change to the settle that moved c past the middle between the two thresholds."""
    mid = 0.5 * (C_BEFORE + C_AFTER)
    return next((k - change_at for k in range(change_at, len(decided)) if decided[k] > mid), None)


@pytest.mark.parametrize("change_at", CHANGES)
def test_a_threshold_that_changes_mid_stream_is_re_estimated_within_check_every_plus_one_frames(two_thresholds,
                                                                                              change_at):
    scene = _jump(two_thresholds, change_at)
    tested, thinned, decided = _run(scene, CHECK_EVERY)
    assert abs(decided[change_at - 1] - C_BEFORE) < 0.03, "c must be found before the jump for the test to count"
    assert all(thinned[change_at - 3:change_at + 1]), "the checks must be thinned when the threshold changes"
    delay = _delay(decided, change_at)
    assert delay is not None, f"c never followed the jump: {decided[change_at:]}"
    assert delay <= MAX_DELAY, (delay, decided[change_at - 1:])
    assert abs(decided[-1] - C_AFTER) < 0.04, (decided[-1], C_AFTER)

    every = _run(scene, 1)
    assert not any(every[1]), "settled_check_every=1 never thins"
    delay_every = _delay(every[2], change_at)
    assert delay_every is not None and delay_every <= 2, "every frame checked, the fit test's patience is 2 frames"
    assert delay - delay_every <= CHECK_EVERY - 1, (delay, delay_every)
    calm = slice(change_at - 8, change_at)
    assert sum(tested[calm]) <= 0.5 * sum(every[0][calm]), "and the thinned run tests c on far fewer frames"


def test_thinned_the_black_level_still_reads_every_pair_it_samples(two_thresholds):
    """The level tables are left out only where neither a fit test nor the black level's pool reads them: with
    rechecks every 10 pairs (pooling 4) in the thinned stretch, the black level's fits see what they see with every
    frame checked (a missing table would fail the sample outright)."""
    from edi_live.black_level_policy import BlackLevelPolicy, BlackLevelSettings

    scene = two_thresholds[0]
    fits = {}
    for every in (1, CHECK_EVERY):
        rec = EdiReconstructor(scene.width, scene.height, c_init=0.2, settled_check_every=every)
        rec._black = rec._calib.black = BlackLevelPolicy(None, BlackLevelSettings(pool_pairs=4, recheck_every=10,
                                                                                  min_pixels=50))
        seen = []
        for k, frame in enumerate(scene.frames):
            stream(dataclasses.replace(scene, frames=[frame], events=scene.events[_event_range(scene, k)]), rec)
            seen.append((rec._black.estimates, dict(rec._black.last_fit)))
        fits[every] = seen
        if every > 1:
            assert rec._calib.tests_skipped >= 10, "the schedule must thin for the test to mean anything"
    assert fits[CHECK_EVERY][-1][0] >= 3, "rechecks must run in the thinned stretch"
    assert fits[CHECK_EVERY] == fits[1]


def test_a_still_scene_whose_events_are_ignored_is_checked_on_every_frame():
    """Its fit test is what notices that the scene moves again; thinned, the latent frames would stand still for
    up to settled_check_every frames longer."""
    scene = make_scene("camera", c_on=0.2, velocity_px_per_ms=(0.0, 0.0), width=64, height=48, n_frames=20,
                       noise_hz=2.0, seed=4)
    rec = EdiReconstructor(scene.width, scene.height, settled_check_every=CHECK_EVERY)
    ignored = []
    for k, frame in enumerate(scene.frames):
        stream(dataclasses.replace(scene, frames=[frame], events=scene.events[_event_range(scene, k)]), rec)
        ignored.append(rec.events_ignored)
    assert sum(ignored) >= 15, "the events must be ignored for most of the scene for the test to mean anything"
    assert rec._calib.tests_skipped == 0 and not rec._calib.schedule.thinned


def test_a_settled_reconstructor_offers_only_pairs_with_both_level_tables(two_thresholds):
    """Thinned, a frame's table is built only where a fit test or the black level reads it; whoever asks for the
    pairs (tools.bench_colour's per-channel c) reads their tables, so a pair without one must not be offered, and
    settled_check_every=1 keeps every pair."""
    scene = two_thresholds[0]
    thinned = EdiReconstructor(scene.width, scene.height, c_init=0.2, settled_check_every=CHECK_EVERY)
    stream(scene, thinned)
    assert thinned._calib.tests_skipped > 0, "the schedule must thin for the test to mean anything"
    assert all(p.prev.table is not None and p.cur.table is not None for p in thinned.pairs)
    assert len(thinned._tracker.pairs) > len(thinned.pairs), "some pair lacks a table: the filter is exercised"
    every = EdiReconstructor(scene.width, scene.height, c_init=0.2, settled_check_every=1)
    stream(scene, every)
    assert every.pairs and len(every.pairs) == len(every._tracker.pairs)


@pytest.mark.parametrize("knob", [{"joint_pairs": 4}, {"reestimate_every": 5}])
def test_pooled_or_periodic_estimates_are_never_thinned(two_thresholds, knob):
    """Joint fits pool the last pairs' tables and a periodic re-estimate counts frames: both need every frame's
    table, so the schedule stays at every frame."""
    scene = two_thresholds[0]
    rec = EdiReconstructor(scene.width, scene.height, c_init=0.2, settled_check_every=CHECK_EVERY, **knob)
    stream(scene, rec)
    assert rec._calib.tests_skipped == 0 and not rec._calib.schedule.enabled
