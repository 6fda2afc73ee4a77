"""Metrics and harness of the accuracy benchmark (tools/accuracy_harness.py, tools/accuracy_methods.py): SSIM/PSNR
against scikit-image, and a tiny end-to-end run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edi_live.simulation import simulate
from tools import accuracy_harness as harness
from tools import accuracy_methods as methods
from tools.simulate import SceneConfig


def test_psnr_matches_the_definition_and_skimage(rng):
    a = rng.uniform(0, 255, (30, 40))
    b = np.clip(a + rng.normal(0, 5, a.shape), 0, 255)
    mse = np.mean((a - b) ** 2)
    assert harness.psnr(a, b) == pytest.approx(10 * math.log10(255 ** 2 / mse))
    from skimage import metrics  # the oracle (test extra): required, never skipped
    assert harness.psnr(a, b) == pytest.approx(metrics.peak_signal_noise_ratio(b, a, data_range=255), rel=1e-9)
    assert harness.psnr(a, a) == float("inf")


def test_ssim_matches_skimage(rng):
    from skimage import metrics  # the oracle (test extra): required, never skipped
    a = rng.uniform(0, 255, (48, 64))
    a = (a + np.roll(a, 1, 0) + np.roll(a, 1, 1)) / 3
    for noise in (1.0, 10.0, 40.0):
        b = np.clip(a + rng.normal(0, noise, a.shape), 0, 255)
        assert harness.ssim(b, a) == pytest.approx(metrics.structural_similarity(b, a, data_range=255), abs=1e-6)
    assert harness.ssim(a, a) == pytest.approx(1.0)


def test_harness_scores_baselines_on_a_tiny_scene():
    cfg = SceneConfig(width=48, height=36, duration_s=0.2, velocity_px_s=(150.0, 0.0), seed=2,
                      frame_interval_us=40_000, exposure_us=20_000, latent_per_interval=2)
    sim = simulate(cfg)
    blurry = harness.score(sim, harness.run_blurry(sim))
    direct = harness.score(sim, methods.run_direct(sim))
    # at f both are the blurry frame; between frames direct integration tracks the motion, the held frame does not
    assert direct.psnr_deblur == pytest.approx(blurry.psnr_deblur)
    assert direct.psnr_latent > blurry.psnr_latent + 1.0
    cf = harness.score(sim, methods.run_complementary(sim, 5.0))
    assert np.isfinite(cf.psnr_latent) and 0 < cf.ssim_latent <= 1
