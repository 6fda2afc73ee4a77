"""The reconstructor on a simulated camera with real-camera effects (edi_live.simulation): separate thresholds
are recovered, a flickering lamp neither drifts nor blooms, noise alone leaves the APS frame as it is, and a given
black level makes the output linear. Ground truth comes from the simulator, never from the code under test."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate


def stream(sim, rec, every: int = 500):
    """Feed a simulation like the worker does: events up to each exposure end, then the frame, latent frames
    every `every` events. Returns (deblurred outputs, [(t_us, latent image)])."""
    ev, t = sim.events, sim.events["t"]
    outs, latent, fed = [], [], 0
    for fr in sim.frames:
        end = int(np.searchsorted(t, fr.exposure_end_us, "right"))
        start = int(np.searchsorted(t, fr.exposure_start_us))
        for i in range(fed, end, every):
            rec.on_events(ev[i:min(i + every, end)])
            if rec.has_reference:
                r = rec.render()
                latent.append((r.t_us, r.image))
        fed = end
        outs.append(rec.on_frame(fr, ev[start:end]))
    return outs, latent


def test_separate_thresholds_are_recovered():
    cfg = SceneConfig(width=120, height=90, duration_s=0.5, texture="camera", velocity_px_s=(150.0, 40.0),
                      c_on=0.25, c_off=0.20, c_sigma=0.0, seed=3)
    rec = EdiReconstructor(cfg.width, cfg.height)
    stream(simulate(cfg), rec)
    assert rec.c_on == pytest.approx(0.25, abs=0.03) and rec.c_off == pytest.approx(0.20, abs=0.03)
    assert rec.c_on > rec.c_off


def test_equal_thresholds_stay_one_c():
    cfg = SceneConfig(width=120, height=90, duration_s=0.5, texture="camera", velocity_px_s=(150.0, 40.0),
                      c_on=0.2, c_off=0.2, seed=3)
    rec = EdiReconstructor(cfg.width, cfg.height)
    stream(simulate(cfg), rec)
    assert rec.c_on == rec.c_off == pytest.approx(0.2, abs=0.03)


def _mean_latent_over_exposures(sim, latent):
    """Per APS frame after the first: the mean of the latent frames inside its exposure (what a viewer saw)."""
    out = []
    for fr in sim.frames[1:]:
        inside = [img.astype(np.float64) for t, img in latent if fr.exposure_start_us <= t <= fr.exposure_end_us]
        if inside:
            out.append((fr.image.astype(np.float64), np.mean(inside, axis=0)))
    return out


@pytest.mark.parametrize("c_off", [0.2, 0.16])
def test_a_flickering_lamp_on_a_still_scene_neither_drifts_nor_blooms(c_off):
    cfg = SceneConfig(width=96, height=72, duration_s=0.6, texture="blocks", velocity_px_s=(0.0, 0.0),
                      flicker_hz=100.0, c_on=0.2, c_off=c_off, c_sigma=0.0, seed=4)
    sim = simulate(cfg)
    assert sim.events.size > 1000, "the lamp must make events for this test to mean anything"
    rec = EdiReconstructor(cfg.width, cfg.height)
    _, latent = stream(sim, rec, every=200)
    pairs = _mean_latent_over_exposures(sim, latent)
    assert len(pairs) >= 5
    for aps, seen in pairs[2:]:  # after start-up: c and the unreliable pixels are known
        assert np.sqrt(np.mean((seen - aps) ** 2)) <= 1.0
        assert np.abs(seen - aps).max() <= 40, "a lamp pixel bloomed"


def test_noise_events_alone_leave_the_aps_frame_as_it_is():
    cfg = SceneConfig(width=96, height=72, duration_s=0.6, texture="blocks", velocity_px_s=(0.0, 0.0),
                      noise_rate_hz=5.0, shot_noise_hz=5.0, seed=6)
    sim = simulate(cfg)
    assert sim.events.size > 500
    rec = EdiReconstructor(cfg.width, cfg.height)
    _, latent = stream(sim, rec, every=100)
    settled = sim.frames[2].exposure_end_us
    for t, img in latent:
        if t <= settled:
            continue
        aps = next(fr.image for fr in reversed(sim.frames) if fr.exposure_end_us <= t)
        assert np.sqrt(np.mean((img.astype(np.float64) - aps) ** 2)) <= 1.0


def test_a_given_black_level_makes_the_frames_linear():
    cfg = SceneConfig(width=120, height=90, duration_s=0.4, texture="camera", velocity_px_s=(150.0, 40.0),
                      aps_offset_dn=10.0, seed=3)
    sim = simulate(cfg)
    # an exact clock, held so (stream() feeds the APS clock; the frames are compared at their mid-exposures)
    plain, _ = stream(sim, EdiReconstructor(cfg.width, cfg.height, black_level=0.0, clock_offset_us=0))
    given, _ = stream(sim, EdiReconstructor(cfg.width, cfg.height, black_level=10.0, clock_offset_us=0))
    assert all(o.black_level == 10.0 for o in given)

    def error(outs):  # mean absolute error against the simulator's sharp frame at each mid-exposure
        return np.mean([np.abs(o.image.astype(float) - sim.gt_at(o.t_us)).mean() for o in outs[2:]])

    assert error(given) < 0.5 * error(plain), (error(given), error(plain))


def test_separate_thresholds_keep_a_moving_scene_with_a_lamp_from_drifting():
    # c_off = 0.8 c_on: with one c, every ON/OFF pair of the lamp and of the moving texture leaves a residue
    cfg = SceneConfig(width=120, height=90, duration_s=0.8, texture="camera", velocity_px_s=(80.0, 20.0),
                      flicker_hz=100.0, c_on=0.2, c_off=0.16, c_sigma=0.0, seed=4)
    sim = simulate(cfg)
    lamp = sim.lamp_mask > 0.5
    assert lamp.any()

    def drift(**settings):
        _, latent = stream(sim, EdiReconstructor(cfg.width, cfg.height, **settings), every=300)
        pairs = _mean_latent_over_exposures(sim, latent)[3:]
        rest = np.mean([np.sqrt(np.mean((seen - aps)[~lamp] ** 2)) for aps, seen in pairs])
        worst_lamp = max(float(np.abs(seen - aps)[lamp].max()) for aps, seen in pairs)
        return rest, worst_lamp

    # the thresholds alone: the flicker mask, which handles the lamp whatever c is, is off here
    rest, lamp_worst = drift(mask_flicker_pixels=False)
    rest_one_c, lamp_worst_one_c = drift(separate_thresholds=False, mask_flicker_pixels=False)
    assert rest < 0.6 * rest_one_c, (rest, rest_one_c)
    assert lamp_worst < lamp_worst_one_c
    # with one c, the flicker mask keeps the moving lamp from drifting as well
    rest_masked, lamp_worst_masked = drift(separate_thresholds=False)
    assert rest_masked < 0.6 * rest_one_c, (rest_masked, rest_one_c)
    assert lamp_worst_masked < lamp_worst_one_c


@pytest.mark.parametrize("flicker_hz", [100.0, 120.0])
def test_a_lamp_with_mismatched_thresholds_stays_put_from_the_first_frame(flicker_hz):
    """c given (no estimation, so no frame-pair check) and 20 % off for OFF events: only the flicker mask, which
    needs no frame pair, keeps the lamp at what the APS frames say, from the first exposure on."""
    cfg = SceneConfig(width=96, height=72, duration_s=0.5, texture="blocks", velocity_px_s=(0.0, 0.0),
                      flicker_hz=flicker_hz, c_on=0.2, c_off=0.16, c_sigma=0.0, seed=4)
    sim = simulate(cfg)
    assert sim.events.size > 1000, "the lamp must make events for this test to mean anything"

    def worst(**settings):
        _, latent = stream(sim, EdiReconstructor(cfg.width, cfg.height, c=0.2, **settings), every=200)
        pairs = _mean_latent_over_exposures(sim, latent)
        assert len(pairs) >= 5
        return max(np.sqrt(np.mean((seen - aps) ** 2)) for aps, seen in pairs), \
            max(np.abs(seen - aps).max() for aps, seen in pairs)

    rms, peak = worst()
    assert rms <= 1.0 and peak <= 40, (rms, peak)
    rms_off, peak_off = worst(mask_flicker_pixels=False)
    assert rms_off > 2 * rms and peak_off > 40, (rms_off, peak_off)  # the scene does need it


def test_a_given_clock_offset_moves_the_exposure_window_into_the_event_clock():
    # events 1.5 ms late against the APS exposure (a real DAVIS's pixel latency): with the offset given, the
    # deblur counts the events that really blurred each frame
    cfg = SceneConfig(width=120, height=90, duration_s=0.4, texture="camera", velocity_px_s=(250.0, 60.0),
                      event_offset_us=1500, seed=3)
    sim = simulate(cfg)

    def error(**settings):
        rec = EdiReconstructor(cfg.width, cfg.height, c=0.2, **settings)
        ev, t = sim.events, sim.events["t"]
        outs, fed = [], 0
        for fr in sim.frames:  # like the worker: events up to the exposure end in the event clock
            end = int(np.searchsorted(t, fr.exposure_end_us + settings.get("clock_offset_us", 0), "right"))
            rec.on_events(ev[fed:end])
            fed = end
            start = int(np.searchsorted(t, fr.exposure_start_us + settings.get("clock_offset_us", 0)))
            outs.append(rec.on_frame(fr, ev[start:end]))
        assert all(o.t_us == fr.mid_exposure_us + settings.get("clock_offset_us", 0)
                   for o, fr in zip(outs, sim.frames))
        return np.mean([np.abs(o.image.astype(float) - sim.gt_at(fr.mid_exposure_us)).mean()
                        for o, fr in zip(outs[1:], sim.frames[1:])])

    assert error(clock_offset_us=1500) < 0.8 * error()


def test_a_given_aps_response_makes_the_frames_linear():
    # APS value = 255 (I/255)^(1/1.15): undoing it before the deblur brings the output onto the linear scale
    cfg = SceneConfig(width=120, height=90, duration_s=0.4, texture="camera", velocity_px_s=(150.0, 40.0),
                      aps_gamma=1.15, seed=3)
    sim = simulate(cfg)
    plain, _ = stream(sim, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=0))  # exact clock, as above
    given, _ = stream(sim, EdiReconstructor(cfg.width, cfg.height, aps_gamma=1.15, clock_offset_us=0))
    assert all(o.aps_gamma == 1.15 for o in given)

    def error(outs):
        return np.mean([np.abs(o.image.astype(float) - sim.gt_at(o.t_us)).mean() for o in outs[2:]])

    assert error(given) < 0.6 * error(plain), (error(given), error(plain))
