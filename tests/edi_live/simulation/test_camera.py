"""The realistic camera effects (edi_live.simulation.camera), each measured on the simulator's output
against what it claims to do, plus what must not change when an effect is off."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from edi_live.simulation import EFFECTS, SceneConfig, linearise_aps, load_ground_truth, preset, save_ground_truth, \
    simulate, with_effects

SMALL = dict(width=64, height=48, duration_s=0.2, frame_interval_us=40_000, exposure_us=20_000,
             first_exposure_us=10_000, latent_per_interval=1, seed=4)


def small(**kw) -> SceneConfig:
    return SceneConfig(**{**SMALL, **kw})


def _per_pixel(ev: np.ndarray, w: int, h: int) -> np.ndarray:
    return np.bincount(ev["y"].astype(np.int64) * w + ev["x"], minlength=w * h)


def test_every_effect_is_off_by_default_and_switches_on_alone():
    base = small()
    for name in EFFECTS:
        cfg = with_effects(base, name)
        changed = {f.name for f in dataclasses.fields(SceneConfig)
                   if getattr(cfg, f.name) != getattr(base, f.name)} - {"effects"}
        assert changed and cfg.effects == (name,), name
    everything = with_effects(base, "all")
    assert set(everything.effects) == set(EFFECTS) and preset("realistic").effects == everything.effects
    with pytest.raises(ValueError, match="unknown camera effect"):
        with_effects(base, "rain")


def test_explicit_settings_win_over_an_effects_values():
    cfg = preset("translate", flicker_hz=120.0, effects=("flicker", "black_level"), aps_offset_dn=4.0)
    assert cfg.flicker_hz == 120.0 and cfg.aps_offset_dn == 4.0


def test_black_level_shifts_the_aps_mean_by_the_set_dn():
    base = simulate(small(velocity_px_s=(0.0, 0.0)))
    dark = simulate(with_effects(small(velocity_px_s=(0.0, 0.0)), "black_level"))
    shift = np.mean([b.image.astype(float).mean() - a.image.astype(float).mean()
                     for a, b in zip(base.frames, dark.frames)])
    assert shift == pytest.approx(dark.config.aps_offset_dn, abs=0.05) and dark.config.aps_offset_dn == 10.0


def test_response_is_the_set_gamma_and_linearise_inverts_it():
    cfg = with_effects(small(velocity_px_s=(150.0, 0.0)), "response", "black_level")
    s = simulate(cfg)
    lin = s.aps_linear[1].astype(np.float64)
    expected = 255.0 * (lin / 255.0) ** (1 / 1.15) + 10.0
    assert np.abs(s.frames[1].image - expected).max() <= 0.5 + 1e-6
    back = linearise_aps(cfg, s.frames[1].image)
    unsaturated = s.frames[1].image < 255
    # 8-bit rounding, carried through the inverse response: at most half a DN times its slope (<= 1.15)
    assert np.abs(back - lin)[unsaturated].max() < 0.6


def test_read_noise_has_the_set_rms():
    cfg = with_effects(small(velocity_px_s=(0.0, 0.0), width=120, height=90), "read_noise")
    s = simulate(cfg)
    resid = np.concatenate([(f.image.astype(float) - lin).ravel() for f, lin in zip(s.frames, s.aps_linear)])
    rms = float(np.sqrt(np.mean(resid ** 2)))
    # Gaussian noise sigma plus uniform rounding error (1/12 DN^2) add in variance
    assert rms == pytest.approx(np.hypot(cfg.aps_noise_dn, np.sqrt(1 / 12)), rel=0.03)


def test_event_clock_offset_shifts_events_against_frames_by_the_set_us():
    base = simulate(small(velocity_px_s=(200.0, 0.0)))
    late = simulate(with_effects(small(velocity_px_s=(200.0, 0.0)), "clock_offset"))
    assert late.config.event_offset_us == 1500
    np.testing.assert_array_equal(late.events["t"], base.events["t"] + 1500)
    for a, b in zip(base.frames, late.frames):
        assert (a.exposure_start_us, a.exposure_end_us) == (b.exposure_start_us, b.exposure_end_us)
        np.testing.assert_array_equal(a.image, b.image)


def test_threshold_ratio_shows_in_the_event_counts_of_a_there_and_back_motion():
    # one full oscillation: every pixel's log intensity returns to its start, so N_on c_on = N_off c_off
    cfg = small(velocity_px_s=(900.0, 0.0), oscillation_period_s=0.1, duration_s=0.5, c_sigma=0.0)
    even = simulate(cfg)
    odd = simulate(with_effects(cfg, "thresholds"))
    c = odd.config
    assert c.c_off == pytest.approx(0.8 * c.c_on) and c.c_sigma == 0.0  # explicit sigma 0 wins
    for s, ratio in ((even, 1.0), (odd, c.c_on / c.c_off)):
        on, off = int(s.events["p"].sum()), int((~s.events["p"]).sum())
        assert off / on == pytest.approx(ratio, rel=0.03)
    spread = simulate(with_effects(small(velocity_px_s=(100.0, 0.0)), "thresholds"))
    assert np.std(spread.c_on_map) == pytest.approx(0.05, rel=0.1)
    assert np.mean(spread.c_off_map) == pytest.approx(0.16, abs=0.005)


def test_refractory_no_two_events_of_a_pixel_closer_than_the_period():
    cfg = with_effects(small(velocity_px_s=(600.0, 0.0), texture="stripes"), "refractory")
    s = simulate(cfg)
    free = simulate(dataclasses.replace(cfg, refractory_us=0))
    ev = s.events
    pix = ev["y"].astype(np.int64) * cfg.width + ev["x"]
    order = np.lexsort((ev["t"], pix))
    gaps = np.diff(ev["t"][order])[pix[order][1:] == pix[order][:-1]]
    assert gaps.min() >= 500 - 1 and s.events.size < free.events.size  # 1 µs: timestamp rounding
    fpix = free.events["y"].astype(np.int64) * cfg.width + free.events["x"]
    forder = np.lexsort((free.events["t"], fpix))
    assert np.diff(free.events["t"][forder])[fpix[forder][1:] == fpix[forder][:-1]].min() < 500  # it can fail


def test_background_rate_is_higher_in_the_dark():
    rate = 40.0
    cfg = small(velocity_px_s=(0.0, 0.0), duration_s=1.0, shot_noise_hz=rate, shot_noise_dark=0.1,
                intensity_range=(0.05, 0.95))
    s = simulate(cfg)
    assert s.is_noise.all()
    counts = _per_pixel(s.events, cfg.width, cfg.height)
    intensity = (s.aps_linear[0] / 255.0).ravel()
    for lo, hi in ((0.0, 0.1), (0.3, 0.5), (0.7, 1.0)):
        sel = (intensity >= lo) & (intensity < hi)
        if sel.sum() < 30:
            continue
        expected = float(np.sum(rate * np.minimum(1.0, 0.1 / intensity[sel]) * 1.0))
        assert abs(counts[sel].sum() - expected) < 5 * np.sqrt(expected), (lo, hi)
    dark = intensity < 0.1
    bright = intensity > 0.5
    assert counts[dark].mean() > 4 * counts[bright].mean()


def test_hot_pixels_fire_at_the_set_rate():
    cfg = with_effects(small(velocity_px_s=(0.0, 0.0), duration_s=1.0), "hot_pixels")
    s = simulate(cfg)
    assert len(s.hot_pixel_xy) == cfg.hot_pixels == 1 and cfg.hot_rate_hz == 150.0
    counts = _per_pixel(s.events, cfg.width, cfg.height).reshape(cfg.height, cfg.width)
    (x, y), = s.hot_pixel_xy
    assert abs(counts[y, x] - 150.0) < 5 * np.sqrt(150.0)
    assert counts.sum() == counts[y, x]


@pytest.mark.parametrize("freq", [100.0, 120.0])
def test_flicker_lamp_fires_on_and_off_at_the_set_frequency(freq):
    cfg = small(velocity_px_s=(0.0, 0.0), duration_s=0.3, flicker_hz=freq, c_sigma=0.0)
    s = simulate(cfg)
    lamp = s.lamp_mask > 0.99
    assert lamp.sum() > 50 and s.lamp_mask[~lamp].max() <= 1.0
    ev = s.events
    assert np.all(s.lamp_mask[ev["y"], ev["x"]] > 0)  # a static scene: only the lamp (and its rim) makes events
    inside = lamp[ev["y"], ev["x"]]
    t = (ev["t"] - cfg.t0_us) * 1e-6
    # ON events while the lamp brightens, OFF while it dims: the phase at the set frequency sorts them
    def rising(f: float) -> np.ndarray:
        phase = (t * f) % 1.0
        return (phase < 0.25) | (phase > 0.75)
    assert rising(freq)[inside & ev["p"]].mean() > 0.95 and rising(freq)[inside & ~ev["p"]].mean() < 0.05
    assert rising(1.1 * freq)[inside & ev["p"]].mean() < 0.8  # at another frequency the phases mix
    # every period brings the lamp back: with c_on = c_off its ON and OFF events balance
    n_on, n_off = int((inside & ev["p"]).sum()), int((inside & ~ev["p"]).sum())
    assert n_on > 20 * 0.3 * freq and abs(n_on - n_off) < 0.05 * (n_on + n_off)
    # the APS integrates the flicker: the lamp's mean over an exposure sits near its mean level
    assert s.aps_linear[0][lamp].mean() / 255 == pytest.approx(cfg.flicker_level, rel=0.1)


def test_ground_truth_file_holds_the_true_camera(tmp_path):
    cfg = preset("realistic", width=64, height=48, duration_s=0.12)
    s = simulate(cfg)
    save_ground_truth(s, tmp_path / "gt.npz")
    cam = load_ground_truth(tmp_path / "gt.npz")["camera"]
    assert (cam["c_on"], cam["c_off"], cam["event_offset_us"], cam["aps_offset_dn"], cam["aps_gamma"],
            cam["refractory_us"], cam["noise_rate_hz"], cam["shot_noise_hz"], cam["hot_rate_hz"],
            cam["flicker_hz"]) == (0.2, 0.16, 1500, 10.0, 1.15, 500, 0.1, 5.0, 150.0, 100.0)
    np.testing.assert_array_equal(cam["c_on_map"], s.c_on_map)
    np.testing.assert_array_equal(cam["c_off_map"], s.c_off_map)
    np.testing.assert_array_equal(cam["hot_pixel_xy"], s.hot_pixel_xy)
    assert cam["flicker_region"] == cfg.flicker_region and set(cam["effects"]) == set(EFFECTS)
    with np.load(tmp_path / "gt.npz") as z:
        np.testing.assert_array_equal(z["lamp_mask"], s.lamp_mask)


def test_ideal_camera_output_is_unchanged_by_the_realistic_camera_code(tmp_path):
    # effects draw from their own random streams: switching the shot noise on adds noise events and leaves the
    # signal events, thresholds and APS frames exactly as they were
    base = simulate(small(velocity_px_s=(200.0, 30.0), noise_rate_hz=2.0, hot_pixels=2))
    again = simulate(small(velocity_px_s=(200.0, 30.0), noise_rate_hz=2.0, hot_pixels=2))
    noisy = simulate(small(velocity_px_s=(200.0, 30.0), noise_rate_hz=2.0, hot_pixels=2, shot_noise_hz=3.0))
    np.testing.assert_array_equal(again.events, base.events)  # deterministic across runs
    np.testing.assert_array_equal(noisy.events[~noisy.is_noise], base.events[~base.is_noise])
    np.testing.assert_array_equal(noisy.c_on_map, base.c_on_map)
    for a, b in zip(base.frames, noisy.frames):
        np.testing.assert_array_equal(a.image, b.image)
    assert noisy.is_noise.sum() > base.is_noise.sum()
    # the ground-truth file of an ideal camera keeps the format it had before the realistic camera existed
    save_ground_truth(base, tmp_path / "gt.npz")
    with np.load(tmp_path / "gt.npz") as z:
        assert set(z.files) == {"gt_t_us", "gt_images", "gt_kind", "gt_frame", "aps_images", "aps_linear",
                                "exposure_start_us", "exposure_end_us", "c_on_map", "c_off_map", "hot_pixel_xy",
                                "n_events", "n_noise_events", "config_json"}
        stored = json.loads(str(z["config_json"]))
    assert "flicker_hz" not in stored and "effects" not in stored and stored["c_sigma"] == 0.03
