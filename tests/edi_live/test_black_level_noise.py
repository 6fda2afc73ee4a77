"""The APS noise as the black-level fit measures it (edi_live.contrast.black_level_noise): sigma from neighbouring
event-free pixels, apart from the scene's own sub-threshold change, and the SIMEX correction of the profile's
minimum, checked against the noise and black level put into synthetic frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.contrast.black_level import QuietSamples
from edi_live.contrast.black_level_noise import (MIN_NOISE_PAIRS, neighbour_differences, read_noise_dn,
                                                 samples_with_noise, simex_black_level)
from edi_live.datatypes import EVENT_DTYPE

H, W = 60, 80


def _smooth_field(rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """A smooth random field on [lo, hi] (a sum of a few long-wave cosines), H x W."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    f = sum(np.cos(rng.uniform(0.02, 0.1) * x + rng.uniform(0.02, 0.1) * y + rng.uniform(0, 6.3)) for _ in range(4))
    f = (f - f.min()) / (f.max() - f.min())
    return lo + (hi - lo) * f


def _pair(sigma: float, rng: np.random.Generator, black: float = 0.0, events_in: np.ndarray | None = None,
          bayer: bool = False, change: float = 0.1, taken_off: float = 0.0, saturation: float | None = None):
    """Two 8-bit frames of one smooth scene whose log intensity changes by up to +-`change` between them (a
    sub-threshold change, no events), with Gaussian noise `sigma` DN; pixels in `events_in` get one ON event
    between the frames and a large change (an edge moved there). `bayer`: seen through an RGGB mosaic whose
    red and blue pixels get 0.4 and 1.6 times the green light. `taken_off`: the frames as the node has them with
    that black level in use (taken off B, the values before it in FrameData.raw); `saturation`: the APS clip."""
    light = _smooth_field(rng, 15.0, 120.0)
    if bayer:
        light[0::2, 0::2] *= 0.4
        light[1::2, 1::2] *= 1.6
    change = np.exp(_smooth_field(rng, -change, change))
    second = light * change
    if events_in is not None:
        second = np.where(events_in, light * 3.0, second)
    frames = []
    for img in (light, second):
        aps = np.clip(np.rint(img + black + sigma * rng.standard_normal(img.shape)), 0, 255).astype(np.uint8)
        b, informative = edi.ApsResponse(saturation, taken_off).to_float(aps)
        raw = edi.blurry_to_float(aps, saturation=saturation)[0] if taken_off else None
        table = edi.build_level_table(np.zeros(0, EVENT_DTYPE), W, H, 0, 1000)
        frames.append(contrast.FrameData(b, informative, table, raw=raw))
    n_on = np.zeros(H * W, np.int64)
    if events_in is not None:
        n_on[events_in.reshape(-1)] = 1
    return contrast.FramePair(frames[0], frames[1], n_on, np.zeros(H * W, np.int64))


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_the_read_noise_is_measured_apart_from_the_scene_change(sigma):
    rng = np.random.default_rng(int(sigma * 10) + 1)
    diff, level = neighbour_differences(_pair(sigma, rng), 0.0)
    s = QuietSamples(np.zeros(0), np.zeros(0), np.zeros(0), diff, level, np.ones(diff.size))
    expected = math.sqrt(sigma ** 2 + 1.0 / 12.0)  # the 8-bit rounding is noise too
    got = read_noise_dn(s, 0.0)
    assert got == pytest.approx(expected, rel=0.2, abs=0.15)


def test_a_bayer_mosaic_is_measured_on_same_colour_neighbours():
    rng = np.random.default_rng(3)
    s = samples_with_noise(_pair(1.0, rng, bayer=True, change=0.3), 0.0)
    direct = s.noise_step == 1  # direct neighbours differ in colour: their changes differ by the texture
    alone = QuietSamples(np.zeros(0), np.zeros(0), np.zeros(0), s.noise_diff[direct], s.noise_level[direct],
                         s.noise_step[direct])
    expected = math.sqrt(1.0 + 1.0 / 12.0)
    assert read_noise_dn(alone, 0.0) > 1.3 * expected  # what direct neighbours alone would say
    assert read_noise_dn(s, 0.0) == pytest.approx(expected, rel=0.2)


def test_pixels_with_events_do_not_enter_the_noise_sample():
    rng = np.random.default_rng(7)
    moved = np.zeros((H, W), bool)
    moved[:, ::3] = True  # every third column: an edge passed (large change, one event)
    pair = _pair(1.0, rng, events_in=moved)
    diff, level = neighbour_differences(pair, 0.0, keep=10 ** 6)
    s = QuietSamples(np.zeros(0), np.zeros(0), np.zeros(0), diff, level, np.ones(diff.size))
    still = ~moved
    assert diff.size == np.count_nonzero(still[:, :-1] & still[:, 1:]) + np.count_nonzero(still[:-1] & still[1:])
    assert read_noise_dn(s, 0.0) == pytest.approx(math.sqrt(1.0 + 1.0 / 12.0), rel=0.2)


@pytest.mark.parametrize("saturation", [None, 200.0])
def test_the_samples_do_not_depend_on_the_black_level_taken_off(saturation):
    """The black-level fit and its noise measurement read the APS values before the black level in use was taken
    off: with 30 DN taken off a 5 DN camera (a start value set too high), the quiet pixels and the neighbour pairs
    must be those of the same frames with nothing taken off, the dark ones below 30 DN included (they carry the
    black level and its noise), and a pixel at the APS clip must stay out."""
    moved = np.zeros((H, W), bool)
    moved[::4, ::3] = True  # some pixels see an edge (one event, a large change): moving quiet samples
    as_is = samples_with_noise(_pair(1.0, np.random.default_rng(5), black=5.0, events_in=moved,
                                     saturation=saturation), 0.0)
    high = samples_with_noise(_pair(1.0, np.random.default_rng(5), black=5.0, events_in=moved, taken_off=30.0,
                                    saturation=saturation), 30.0)
    assert np.count_nonzero(as_is.noise_level <= 30.0) > MIN_NOISE_PAIRS  # the frames have such dark pixels
    for key in ("b_prev", "b_cur", "net", "noise_diff", "noise_level", "noise_step"):
        np.testing.assert_array_equal(getattr(high, key), getattr(as_is, key), err_msg=key)


def test_simex_undoes_the_noise_bias_of_the_profile():
    """Quiet samples with a known black level: ratios are c * N up to a small dead-band error, APS noise 1.5 DN.
    The profile's minimum is pulled low by the noise; the extrapolation to no noise lands near the truth."""
    rng = np.random.default_rng(11)
    n, c, black, sigma = 20000, 0.2, 10.0, 1.5
    light = np.exp(rng.uniform(math.log(8.0), math.log(200.0), n))
    net = rng.integers(-2, 3, n).astype(np.float64)
    second = light * np.exp(c * net + rng.uniform(-0.05, 0.05, n))
    b_prev = np.rint(light + black + sigma * rng.standard_normal(n))
    b_cur = np.rint(second + black + sigma * rng.standard_normal(n))
    keep = (b_prev >= 3) & (b_cur >= 3) & (b_prev <= 250) & (b_cur <= 250)
    s = QuietSamples(b_prev[keep], b_cur[keep], net[keep])
    corrected, steps = simex_black_level(s, math.sqrt(sigma ** 2 + 1.0 / 12.0))
    raw = steps[0]
    assert steps[2] < steps[1] < raw  # more noise, lower minimum: the bias being undone
    assert abs(corrected - black) < abs(raw - black)
    assert abs(corrected - black) <= 2.0, (raw, corrected)


def test_the_noise_correction_works_on_a_capped_sample_that_keeps_every_moving_pixel():
    """A large pool (a still, mostly event-free sensor) is cut to SIMEX_MAX_SAMPLES before the correction's ~9
    profile searches: all pixels with a net count stay (they carry the black level), the rest are sampled."""
    from edi_live.contrast.black_level import QuietSamples
    from edi_live.contrast.black_level_noise import _capped

    rng = np.random.default_rng(0)
    n = 100_000
    net = np.where(rng.random(n) < 0.05, rng.integers(-3, 4, n), 0).astype(np.float64)
    s = QuietSamples(rng.uniform(3, 250, n), rng.uniform(3, 250, n), net)
    capped = _capped(s, 30_000, np.random.default_rng(1))
    assert capped.size == 30_000
    assert np.count_nonzero(capped.net) == np.count_nonzero(net)
    assert _capped(s, n, np.random.default_rng(1)) is s
