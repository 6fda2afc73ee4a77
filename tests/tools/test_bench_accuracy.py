"""Metrics and harness of tools/bench_accuracy.py: SSIM/PSNR against scikit-image, and a tiny end-to-end run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tools import bench_accuracy as ba
from tools.simulate import SceneConfig


def test_psnr_matches_the_definition_and_skimage(rng):
    a = rng.uniform(0, 255, (30, 40))
    b = np.clip(a + rng.normal(0, 5, a.shape), 0, 255)
    mse = np.mean((a - b) ** 2)
    assert ba.psnr(a, b) == pytest.approx(10 * math.log10(255 ** 2 / mse))
    from skimage import metrics  # the oracle (test extra): required, never skipped
    assert ba.psnr(a, b) == pytest.approx(metrics.peak_signal_noise_ratio(b, a, data_range=255), rel=1e-9)
    assert ba.psnr(a, a) == float("inf")


def test_ssim_matches_skimage(rng):
    from skimage import metrics  # the oracle (test extra): required, never skipped
    a = rng.uniform(0, 255, (48, 64))
    a = (a + np.roll(a, 1, 0) + np.roll(a, 1, 1)) / 3
    for noise in (1.0, 10.0, 40.0):
        b = np.clip(a + rng.normal(0, noise, a.shape), 0, 255)
        assert ba.ssim(b, a) == pytest.approx(metrics.structural_similarity(b, a, data_range=255), abs=1e-6)
    assert ba.ssim(a, a) == pytest.approx(1.0)


def test_harness_scores_baselines_on_a_tiny_scene():
    cfg = SceneConfig(width=48, height=36, duration_s=0.2, velocity_px_s=(150.0, 0.0), seed=2,
                      frame_interval_us=40_000, exposure_us=20_000, latent_per_interval=2)
    sim = ba.simulate(cfg)
    blurry = ba.score(sim, ba.run_blurry(sim))
    direct = ba.score(sim, ba.run_direct(sim))
    # at f both are the blurry frame; between frames direct integration tracks the motion, the held frame does not
    assert direct.psnr_deblur == pytest.approx(blurry.psnr_deblur)
    assert direct.psnr_latent > blurry.psnr_latent + 1.0
    cf = ba.score(sim, ba.run_complementary(sim, 5.0))
    assert np.isfinite(cf.psnr_latent) and 0 < cf.ssim_latent <= 1


def _tiny(**kw):
    from edi_live.simulation import preset
    return preset("translate", width=64, height=48, duration_s=0.2, frame_interval_us=40_000, exposure_us=20_000,
                  velocity_px_s=(150.0, 30.0), latent_per_interval=2, seed=3, **kw)


def test_oracle_inputs_undo_the_true_camera():
    from edi_live.simulation import with_effects
    ideal = ba.simulate(_tiny())
    real = ba.simulate(with_effects(_tiny(), "clock_offset", "black_level", "response", "hot_pixels"))
    ev, frames = ba.oracle_inputs(real)
    hot = {tuple(xy) for xy in real.hot_pixel_xy}
    assert hot and not any((int(e["x"]), int(e["y"])) in hot for e in ev)
    keep = np.array([(int(x), int(y)) not in hot for x, y in zip(ideal.events["x"], ideal.events["y"])])
    signal = ideal.events[keep]
    np.testing.assert_array_equal(ev["t"][: signal.size], signal["t"])  # back on the APS clock
    for (b, informative), lin in zip(frames, real.aps_linear):
        assert np.abs(b - lin)[informative].max() < 0.6  # linear again, up to 8-bit rounding


def test_oracle_camera_is_plain_edi_on_an_ideal_camera_and_wins_on_a_real_one():
    ideal = ba.simulate(_tiny())
    a, b = ba.run_oracle_camera(ideal), ba.run_edi_functions(ideal)
    for g in a.deblurred:
        np.testing.assert_allclose(a.deblurred[g][0], b.deblurred[g][0], rtol=1e-6)
    from edi_live.simulation import with_effects
    real = ba.simulate(with_effects(_tiny(), "black_level", "response", "clock_offset"))
    oracle = ba.score(real, ba.run_oracle_camera(real))
    default = ba.score(real, ba.run_reconstructor(real))
    assert oracle.psnr_deblur > default.psnr_deblur + 3.0 and oracle.psnr_latent > default.psnr_latent


def test_realistic_section_runs_quick(capsys):
    assert ba.main(["--realistic", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "default - oracle f / lat (dB)" in out and "given - oracle f / lat (dB)" in out
    assert "mean of the 2 mixed scenes" in out and "all effects" in out
    assert len([ln for ln in out.splitlines() if ln.startswith("| ") and "PSNR" not in ln]) == 4
    full = ba.realistic_suite()
    from edi_live.simulation import EFFECTS
    assert sum(g == "mix" for g, _, _ in full) >= 5
    assert {lab.split(": ")[1] for g, lab, _ in full if g == "alone"} >= {f"{n} alone" for n in EFFECTS}
