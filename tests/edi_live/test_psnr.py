"""psnr_pair against PSNR written out in float64, and its edge cases (a perfect match, no pixel)."""

import math

import numpy as np

from edi_live.psnr import PSNR_CAP_DB, psnr_pair, to_8bit_scale


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    d = a.astype(np.float64)[mask] - b.astype(np.float64)[mask]
    return 10 * math.log10(255.0**2 / np.mean(d * d))


def test_psnr_pair_matches_the_definition_on_valid_and_active_pixels():
    rng = np.random.default_rng(3)
    target = rng.integers(0, 256, (30, 40)).astype(np.float32)
    prediction = (target + rng.normal(0, 6, target.shape)).astype(np.float32)
    valid = rng.random(target.shape) > 0.2
    active = rng.random(target.shape) > 0.7
    idx = np.flatnonzero(active & valid)
    whole, part = psnr_pair(prediction, target, valid, int(valid.sum()), idx)
    assert math.isclose(whole, _psnr(prediction, target, valid), abs_tol=1e-4)
    assert math.isclose(part, _psnr(prediction, target, active & valid), abs_tol=1e-4)


def test_psnr_pair_caps_a_perfect_match_and_gives_none_without_pixels():
    img = np.full((4, 5), 17, np.float32)
    valid = np.ones(img.shape, bool)
    assert psnr_pair(img, img, valid, img.size, np.arange(3)) == (PSNR_CAP_DB, PSNR_CAP_DB)
    assert psnr_pair(img, img + 1, np.zeros(img.shape, bool), 0, None) == (None, None)


def test_to_8bit_scale_marks_clipped_and_non_finite_values_uninformative():
    b, valid = to_8bit_scale(np.array([[0, 1, 128, 65535]], np.uint16))
    assert b[0, 2] == np.float32(128 * 255 / 65535) and valid.tolist() == [[False, True, True, False]]
    b, valid = to_8bit_scale(np.array([[np.nan, 3.0, np.inf]], np.float32))
    assert np.isfinite(b).all() and valid.tolist() == [[False, True, False]]
