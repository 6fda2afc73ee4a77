"""Physics of the ESIM-style simulator (edi_live.simulation), checked against independent oracles.

Oracles: brute-force time integration of the scene, the threshold-crossing invariant computed from rendered
log frames, Poisson statistics, and dv-processing reading back the written .aedat4.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from edi_live.datatypes import EVENT_DTYPE
from edi_live.simulation import SceneConfig, load_ground_truth, preset, save_ground_truth, simulate
from edi_live.simulation.events import signal_events
from edi_live.simulation.motion import Renderer

SMALL = dict(width=64, height=48, duration_s=0.2, frame_interval_us=40_000, exposure_us=20_000,
             first_exposure_us=10_000, latent_per_interval=3, seed=3)


def small(**kw) -> SceneConfig:
    return SceneConfig(**{**SMALL, **kw})


def _log_at(cfg: SceneConfig, step_us: int, t_rel_us: float) -> np.ndarray:
    """The scene's log intensity at t: log-linear between the render grid samples (its definition)."""
    r = Renderer(cfg)
    k = int(t_rel_us // step_us)
    a = (t_rel_us - k * step_us) / step_us
    l0 = r.log_frame(k * step_us * 1e-6).astype(np.float64)
    if a == 0:
        return l0
    l1 = r.log_frame((k + 1) * step_us * 1e-6).astype(np.float64)
    return l0 + a * (l1 - l0)


def test_events_have_the_contract_dtype_and_are_time_ordered():
    s = simulate(small(velocity_px_s=(200.0, 50.0), noise_rate_hz=2.0, hot_pixels=2))
    assert s.events.dtype == EVENT_DTYPE
    assert np.all(np.diff(s.events["t"]) >= 0)
    t0 = s.config.t0_us
    assert s.events["t"].min() >= t0 and s.events["t"].max() <= t0 + 200_000
    assert s.events["x"].max() < 64 and s.events["y"].max() < 48
    # timestamps are interpolated between render steps, not snapped to them
    on_grid = np.mean((s.events["t"][~s.is_noise] - t0) % s.step_us == 0)
    assert on_grid < 0.2


def test_static_scene_without_noise_gives_no_events():
    s = simulate(small(velocity_px_s=(0.0, 0.0)))
    assert s.events.size == 0
    assert len(s.frames) == 5


def test_static_scene_events_are_only_noise_with_poisson_rate():
    rate_hz, hot, hot_rate = 5.0, 3, 1000.0
    s = simulate(small(velocity_px_s=(0.0, 0.0), noise_rate_hz=rate_hz, hot_pixels=hot, hot_rate_hz=hot_rate))
    assert s.is_noise.all()
    expected = rate_hz * 64 * 48 * 0.2 + hot * hot_rate * 0.2
    assert abs(s.events.size - expected) < 5 * np.sqrt(expected)
    # the hot pixels are where the simulator says, and fire at their rate
    for x, y in s.hot_pixel_xy:
        n = np.count_nonzero((s.events["x"] == x) & (s.events["y"] == y))
        assert abs(n - hot_rate * 0.2) < 6 * np.sqrt(hot_rate * 0.2) + 2


def test_static_scene_aps_frame_equals_the_texture_and_ground_truth():
    s = simulate(small(velocity_px_s=(0.0, 0.0)))
    tex = 255.0 * np.exp(Renderer(s.config).log_frame(0.0).astype(np.float64))
    for f, lin in zip(s.frames, s.aps_linear):
        np.testing.assert_allclose(lin, tex, rtol=1e-5)
        assert np.abs(f.image.astype(float) - tex).max() <= 0.5 + 1e-3  # rounded to 8 bits
    np.testing.assert_allclose(s.gt_images, np.broadcast_to(tex, s.gt_images.shape), rtol=1e-5)


def test_aps_frame_is_the_mean_of_linear_intensity_over_the_exposure():
    cfg = small(velocity_px_s=(300.0, -80.0), rotation_deg_s=40.0, zoom_per_s=0.3)
    s = simulate(cfg)
    f = s.frames[2]
    ts, te = f.exposure_start_us - cfg.t0_us, f.exposure_end_us - cfg.t0_us
    # brute force: many sub-steps per render step of the scene's own (log-linear) time course
    sub = 16
    times = ts + (np.arange((te - ts) // s.step_us * sub) + 0.5) * s.step_us / sub
    mean = np.mean([np.exp(_log_at(cfg, s.step_us, t)) for t in times], axis=0) * 255.0
    np.testing.assert_allclose(s.aps_linear[2], mean, rtol=2e-4)
    # and against frames rendered directly at those times (no interpolation): only the render grid differs
    r = Renderer(cfg)
    direct = np.mean([np.exp(r.log_frame(t * 1e-6).astype(np.float64)) for t in times[::4]], axis=0) * 255.0
    assert np.abs(s.aps_linear[2] - direct).mean() < 0.5
    # the 8-bit frame is that mean, rounded
    assert np.abs(f.image.astype(float) - s.aps_linear[2]).max() <= 0.5 + 1e-3
    # motion blur is real: the frame differs from the sharp mid-exposure ground truth
    gt = s.gt_at(f.mid_exposure_us)
    assert np.abs(gt - s.aps_linear[2]).mean() > 2.0


def test_ground_truth_matches_the_rendered_scene_at_its_times():
    cfg = small(velocity_px_s=(150.0, 40.0), rotation_deg_s=20.0, gt_extra_us=(77_777, 3_001))
    s = simulate(cfg)
    assert np.all(np.diff(s.gt_t_us) > 0)
    assert set(s.gt_kind.tolist()) == {0, 1, 2}
    extra = np.flatnonzero(s.gt_kind == 2)
    np.testing.assert_array_equal(s.gt_t_us[extra] - cfg.t0_us, [3_001, 77_777])
    for i in (0, 3, len(s.gt_t_us) - 1, *extra):
        expected = 255.0 * np.exp(_log_at(cfg, s.step_us, s.gt_t_us[i] - cfg.t0_us))
        np.testing.assert_allclose(s.gt_images[i], expected, rtol=1e-4)
    mids = s.gt_t_us[s.gt_kind == 0]
    np.testing.assert_array_equal(mids, s.mid_exposure_us)


@pytest.mark.parametrize("c_on,c_off,sigma", [(0.2, 0.2, 0.0), (0.15, 0.3, 0.03)])
def test_event_counts_follow_log_intensity_change_over_the_thresholds(c_on, c_off, sigma):
    cfg = small(velocity_px_s=(220.0, 60.0), rotation_deg_s=30.0, c_on=c_on, c_off=c_off, c_sigma=sigma)
    s = simulate(cfg)
    h, w = cfg.height, cfg.width
    if sigma == 0:
        assert np.allclose(s.c_on_map, c_on) and np.allclose(s.c_off_map, c_off)
    else:
        assert 0.5 * sigma < np.std(s.c_on_map) < 1.5 * sigma
    ev = s.events
    n_on = np.bincount(ev["y"][ev["p"]].astype(int) * w + ev["x"][ev["p"]], minlength=w * h).reshape(h, w)
    n_off = np.bincount(ev["y"][~ev["p"]].astype(int) * w + ev["x"][~ev["p"]], minlength=w * h).reshape(h, w)
    end_rel = (int(round(cfg.duration_s * 1e6)) // s.step_us) * s.step_us
    dlog = _log_at(cfg, s.step_us, end_rel) - _log_at(cfg, s.step_us, 0)
    residual = dlog - (s.c_on_map * n_on - s.c_off_map * n_off)
    # ESIM invariant: the reference level stays within one threshold of the current level
    assert np.all(residual < s.c_on_map + 1e-4)
    assert np.all(residual > -s.c_off_map - 1e-4)


def test_monotone_log_ramp_gives_floor_count_at_exact_crossing_times():
    # the crossing kernel on its own: 5 pixels whose log level rises linearly at different rates
    rates = np.array([1.1, 2.3, 7.3, -3.1, 0.05])  # log units per second
    c = np.full(5, 0.2, np.float32)
    ref = np.zeros(5, np.float32)
    last = np.full(5, -np.inf)
    dt = 0.001
    got_pix, got_t = [], []
    for k in range(400):
        l0 = (rates * k * dt).astype(np.float32)
        l1 = (rates * (k + 1) * dt).astype(np.float32)
        pix, t, pol = signal_events(ref, l0, l1, c, c, k * dt, dt, 0.0, last)
        assert np.all(pol == (rates[pix] > 0))
        got_pix.append(pix), got_t.append(t)
    pix, t = np.concatenate(got_pix), np.concatenate(got_t)
    total = rates * 0.4
    np.testing.assert_array_equal(np.bincount(pix, minlength=5), np.floor(np.abs(total) / np.float64(np.float32(0.2))))
    for i in range(5):
        ti = np.sort(t[pix == i])
        expected = np.arange(1, ti.size + 1) * 0.2 / abs(rates[i])
        np.testing.assert_allclose(ti, expected, atol=2e-6)


def test_refractory_period_spaces_events_at_each_pixel():
    refr = 2_000
    cfg = small(velocity_px_s=(600.0, 0.0), texture="stripes", refractory_us=refr)
    s = simulate(cfg)
    free = simulate(dataclasses.replace(cfg, refractory_us=0))
    assert 0 < s.events.size < free.events.size
    ev = s.events
    pix = ev["y"].astype(np.int64) * cfg.width + ev["x"]
    order = np.lexsort((ev["t"], pix))
    same = pix[order][1:] == pix[order][:-1]
    gaps = np.diff(ev["t"][order])[same]
    assert gaps.min() >= refr - 1  # 1 µs for timestamp rounding


def test_presets_and_resolutions():
    cfg = preset("davis346", texture="noise", duration_s=0.12)
    assert (cfg.width, cfg.height) == (346, 260)
    s = simulate(cfg)
    assert s.frames[0].image.shape == (260, 346) and s.events.size > 0
    with pytest.raises(ValueError, match="unknown preset"):
        preset("nope")
    with pytest.raises(ValueError, match="unknown texture"):
        simulate(small(texture="nope"))


def test_ground_truth_npz_round_trip(tmp_path):
    s = simulate(small(velocity_px_s=(100.0, 0.0)))
    save_ground_truth(s, tmp_path / "gt.npz")
    gt = load_ground_truth(tmp_path / "gt.npz")
    np.testing.assert_array_equal(gt["gt_t_us"], s.gt_t_us)
    np.testing.assert_array_equal(gt["gt_images"], s.gt_images)
    np.testing.assert_array_equal(gt["aps_images"][1], s.frames[1].image)
    assert gt["config"]["width"] == 64 and int(gt["n_events"]) == s.events.size


def test_aps_offset_gamma_and_event_offset_are_applied():
    base = simulate(small(velocity_px_s=(120.0, 0.0)))
    odd = simulate(small(velocity_px_s=(120.0, 0.0), aps_offset_dn=10.0, aps_gamma=2.0, event_offset_us=-7))
    np.testing.assert_array_equal(odd.aps_linear, base.aps_linear)  # the truth stays linear
    expected = np.clip(np.rint(255.0 * (base.aps_linear[1] / 255.0) ** 0.5 + 10.0), 0, 255)
    assert np.abs(odd.frames[1].image.astype(float) - expected).max() <= 1
    np.testing.assert_array_equal(odd.events["t"], base.events["t"] - 7)
