"""The event clock offset from two APS frames (edi_live.contrast.clock_offset), on scenes built here with the
simulator: with the step model's lag taken out first (midlevel_times), a 1.5 ms offset is found within 0.3 ms and
an ideal camera gives ~0."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.contrast.clock_offset import FrameWindow, estimate_clock_offset, midlevel_times
from edi_live.datatypes import EVENT_DTYPE
from edi_live.simulation import preset, simulate, with_effects


def _median_offset(cfg, pairs: int = 6, *, midlevel: bool = True) -> float:
    sim = simulate(cfg)
    h, w = cfg.height, cfg.width
    sample = np.zeros(h * w, bool)
    sample[np.random.default_rng(0).choice(h * w, 4000, replace=False)] = True
    ev = midlevel_times(sim.events, w) if midlevel else sim.events
    frames = [FrameWindow(f.exposure_start_us, f.exposure_end_us, f.image.astype(np.float64),
                          (f.image > 0) & (f.image < 255)) for f in sim.frames]
    found = []
    for a, b in list(zip(frames[1:-1], frames[2:]))[:pairs]:
        t = ev["t"]
        sub = ev[(t >= a.exposure_start_us - 5000) & (t <= b.exposure_end_us + 5000)]
        d = estimate_clock_offset(sub, a, b, sample.reshape(h, w), (cfg.c_on, cfg.c_off))
        if d is not None:
            found.append(d)
    assert len(found) >= pairs // 2
    return float(np.median(found))


@pytest.fixture(scope="module")
def scene():
    return preset("translate", texture="camera", velocity_px_s=(200.0, 50.0), duration_s=0.45, seed=21,
                  ground_truth=False)


def test_a_late_event_clock_is_found_within_0_3_ms(scene):
    cfg = with_effects(scene, "clock_offset")  # events 1.5 ms late
    assert abs(_median_offset(cfg) - cfg.event_offset_us) <= 300


def test_an_ideal_camera_gives_no_offset_once_the_step_lag_is_out(scene):
    assert abs(_median_offset(scene)) <= 300
    # without the mid-level times the fit absorbs the step model's lag (why it is taken out)
    assert _median_offset(scene, pairs=3, midlevel=False) > 1000


def test_midlevel_times_move_each_event_half_way_back_to_its_predecessor():
    ev = np.zeros(4, EVENT_DTYPE)
    ev["t"] = [100, 200, 400, 50_000]
    ev["x"] = [1, 2, 1, 1]
    ev["p"] = [1, 1, 1, 1]
    out = midlevel_times(ev, width=4, max_gap_us=10_000)
    assert sorted(out["t"].tolist()) == [100, 200, 250, 50_000 - 5_000]


def _stream(sim, rec):
    """Feed as the worker does: each exposure's events in the event clock (moved by the offset in use)."""
    ev, frames = sim.events, sim.frames
    t = ev["t"]

    def between(t0, t1):
        return ev[np.searchsorted(t, t0, "left"):np.searchsorted(t, t1, "right")]
    for k, f in enumerate(frames):
        off = rec.clock_offset_us
        rec.on_frame(f, between(f.exposure_start_us + off, f.exposure_end_us + off))
        if k + 1 < len(frames):
            rec.on_events(between(f.exposure_end_us + off + 1, frames[k + 1].exposure_end_us + rec.clock_offset_us))
    return rec


def test_the_reconstructor_finds_the_offset_when_asked_and_keeps_a_given_one(scene):
    import dataclasses

    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(dataclasses.replace(scene, duration_s=1.2), "clock_offset")
    sim = simulate(cfg)
    rec = _stream(sim, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None))
    assert abs(rec.clock_offset_us - cfg.event_offset_us) <= 300, rec._clock.last_estimates
    assert rec.stats()["clock_offset_estimated"]
    given = _stream(sim, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=700))
    assert given.clock_offset_us == 700 and not given.stats()["clock_offset_estimated"]
