"""The deblur's correction smoothed across neighbours (edi.smoothing): the 3x3 median of log D at the active pixels,
and what the reconstructor makes of it (the deblurred frame and the latent start at te; the reference untouched)."""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import preset, simulate
from tests.edi_live.edi_scenes import psnr


def _brute_median(pixels, values, width, height, step):
    """The definition, one pixel at a time: 9 neighbours `step` apart, 0 where not active, the pixel itself where
    off the sensor."""
    grid = {int(q): float(v) for q, v in zip(pixels, values)}
    out = []
    for q in pixels:
        y, x = divmod(int(q), width)
        around = []
        for dy in (-step, 0, step):
            for dx in (-step, 0, step):
                yy = y + dy if 0 <= y + dy < height else y
                xx = x + dx if 0 <= x + dx < width else x
                around.append(grid.get(yy * width + xx, 0.0))
        out.append(sorted(around)[4])
    return np.array(out)


@pytest.mark.parametrize("reference", [False, True])
@pytest.mark.parametrize("step", [1, 2])
def test_the_median_is_the_nine_neighbour_median_of_its_definition(rng, reference, step):
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(1, 14, 2))
        pixels = np.sort(rng.choice(h * w, int(rng.integers(0, h * w + 1)), replace=False))
        values = rng.normal(0, 1, pixels.size) * (rng.random(pixels.size) < 0.9)
        if reference:
            with edi.numpy_reference():
                got = edi.median_at_pixels(pixels, values, w, h, step)
        else:
            got = edi.median_at_pixels(pixels, values, w, h, step)
        assert np.array_equal(got, _brute_median(pixels, values, w, h, step))


def test_a_lone_pixel_loses_its_correction_and_an_edge_keeps_its_own():
    h, w = 9, 12
    grid = np.zeros((h, w))
    grid[:, 6:] = 0.8  # an edge: every pixel right of it has the same log D
    grid[2, 2] = 1.5  # one pixel alone on the quiet side
    pixels = np.flatnonzero(grid)
    med = edi.median_at_pixels(pixels, grid.reshape(-1)[pixels], w, h)
    out = np.zeros(h * w)
    out[pixels] = med
    out = out.reshape(h, w)
    assert out[2, 2] == 0.0
    assert np.array_equal(out[:, 6:], grid[:, 6:])


def test_on_a_mosaic_only_the_pixels_own_colour_counts():
    """step 2: a pixel's neighbours are the same-colour pixels two apart; busy pixels of the other colours around
    it do not keep a lone correction alive."""
    h, w = 8, 8
    grid = np.zeros((h, w))
    grid[1::2, :] = 0.7  # odd rows (other colours) all active
    grid[0::2, 1::2] = 0.7  # and the other colour of the even rows
    grid[4, 4] = 1.2  # one pixel of the even-row, even-column colour; its own colour is quiet around it
    pixels = np.flatnonzero(grid)
    at = int(np.searchsorted(pixels, 4 * w + 4))
    assert edi.median_at_pixels(pixels, grid.reshape(-1)[pixels], w, h, step=2)[at] == 0.0
    assert edi.median_at_pixels(pixels, grid.reshape(-1)[pixels], w, h, step=1)[at] == pytest.approx(0.7)


def _still_frame_with_one_event(width=24, height=18):
    """A flat grey APS frame, and one ON event at one pixel in the middle of its exposure (noise)."""
    image = np.full((height, width), 120, np.uint8)
    frame = Frame(image=image, exposure_start_us=1_000, exposure_end_us=21_000)
    ev = np.zeros(1, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = 6_000, 7, 5, True
    return frame, ev


@pytest.mark.parametrize("reference", [False, True])
def test_a_lone_noise_event_does_not_speckle_the_deblurred_frame(reference):
    """Plain EDI divides the pixel by its own integral and shows a bright dot; with the median it shows B there, and
    the latent image at te too; the per-pixel reference (what the tests and the other modes read) is EDI's own."""
    frame, ev = _still_frame_with_one_event()
    outs = {}
    for median in (True, False):
        rec = EdiReconstructor(24, 18, c=0.3, divisor_median=median, black_level=0.0, clock_offset_us=0)
        if reference:
            with edi.numpy_reference():
                out = rec.on_frame(frame, ev)
        else:
            out = rec.on_frame(frame, ev)
        outs[median] = (out.image.copy(), rec.reference_log()[0].copy(), rec.render().image.copy())
    (img_m, ref_m, lat_m), (img_p, ref_p, lat_p) = outs[True], outs[False]
    assert img_p[5, 7] >= 120 + 5  # an ON step before f: plain EDI takes the exposure as darker and brightens L(f)
    assert np.all(img_m == 120)
    assert np.array_equal(ref_m, ref_p)
    assert lat_m[5, 7] == 120 and lat_p[5, 7] != 120


def test_the_median_gains_at_mid_exposure_on_a_simulated_scene():
    """The point of it: deblurred frames closer to the ground truth than per-pixel EDI with the same c (+2 dB on
    the benchmark suites; here a small scene with threshold mismatch and noise), latent frames no worse."""
    cfg = dataclasses.replace(preset("translate", texture="camera", velocity_px_s=(200.0, 50.0), duration_s=0.3,
                                     seed=5, noise_rate_hz=0.5), width=120, height=90, c_sigma=0.03)
    sim = simulate(cfg)
    mids = {int(sim.gt_frame[i]): i for i in np.flatnonzero(sim.gt_kind == 0)}
    scores = {}
    for median in (True, False):
        rec = EdiReconstructor(cfg.width, cfg.height, c=cfg.c_on, divisor_median=median, black_level=0.0,
                               clock_offset_us=0)
        got = []
        lo = -(2**62)
        for k, f in enumerate(sim.frames):
            ev = sim.events[(sim.events["t"] > lo) & (sim.events["t"] <= f.exposure_end_us)]
            lo = f.exposure_end_us
            out = rec.on_frame(f, ev)
            if k >= 1 and k in mids:
                got.append(psnr(out.image, sim.gt_images[mids[k]]))
        scores[median] = float(np.mean(got))
    assert scores[True] > scores[False] + 0.5, scores


def test_the_smoothed_divisor_is_the_rounded_median_on_one_kept_scratch_and_refuses_a_wrong_one(rng):
    """smoothed_divisor (the reconstructor's call): float32 medians of log D and of log D - exponent, equal to the
    definition's medians rounded (rounding is monotonic), compiled and numpy alike, frame after frame on one scratch
    grid (dense and per-pixel passes), which it leaves zeroed; a scratch of the wrong kind is refused."""
    h, w = 10, 14
    scratch = edi.new_median_scratch(w, h)
    for n in (60, 5, 140, 20, 90):
        pixels = np.sort(rng.choice(h * w, n, replace=False))
        log_d, delta = rng.normal(0, 1, n), rng.normal(0, 1, n)
        shown, jump = edi.smoothed_divisor((pixels, log_d, delta), w, h, scratch=scratch)
        with edi.numpy_reference():
            ref = edi.smoothed_divisor((pixels, log_d, delta), w, h)
        want = _brute_median(pixels, log_d, w, h, 1).astype(np.float32)
        want_te = _brute_median(pixels, (log_d - delta).astype(np.float32), w, h, 1).astype(np.float32)
        assert shown.dtype == jump.dtype == np.float32
        assert np.array_equal(shown, want) and np.array_equal(jump, want - want_te)
        assert np.array_equal(shown, ref[0]) and np.array_equal(jump, ref[1])
        assert not scratch[0].any()
    with pytest.raises(ValueError, match="scratch"):
        edi.smoothed_divisor((pixels, log_d, delta), w, h, scratch=np.zeros((2, h * w)))


def _brute_start(image, aps, divisor, step):
    """The definition of the smoothed deblur, pixel by pixel: (log L(f) of each pixel's own log D, log L(f) of the
    median, the latent log image at te: that plus median(log D) - median(log D - the f -> te exponent))."""
    pixels, log_d, delta = divisor
    h, w = image.shape
    b, informative = aps.to_float(image)
    log_b = np.clip(np.log(np.maximum(b.reshape(-1).astype(np.float64), edi.DARK_FLOOR)), edi.LOG_MIN, edi.LOG_MAX)
    med = _brute_median(pixels, log_d, w, h, step)
    med_te = med if delta is None else _brute_median(pixels, log_d - delta, w, h, step)
    own, shown = log_b.copy(), log_b.copy()
    use = informative.reshape(-1)[pixels]
    own[pixels[use]] = np.clip(log_b[pixels[use]] - log_d[use], edi.LOG_MIN, edi.LOG_MAX)
    shown[pixels[use]] = np.clip(log_b[pixels[use]] - med[use], edi.LOG_MIN, edi.LOG_MAX)
    lat = shown.copy()
    lat[pixels] = np.clip(shown[pixels] + med - med_te, edi.LOG_MIN, edi.LOG_MAX)
    return own.reshape(h, w), shown.reshape(h, w), lat.reshape(h, w)


@pytest.mark.parametrize("reference", [False, True])
@pytest.mark.parametrize("step", [1, 2])
def test_the_reference_the_frame_and_the_latent_start_follow_their_definition(rng, reference, step):
    """LatentState.set_reference with the median, on every path (uint8 frames with the f -> te exponent: one
    compiled pass or its numpy reference; uint16 frames and divisors without the exponent: the general path), with
    a black level and gamma, saturated and dark pixels, read-only frames and values past the log clip."""
    from edi_live.latent_state import LatentState

    for trial in range(60):
        h, w = (int(v) for v in rng.integers(2, 12, 2))
        dtype = np.uint16 if trial % 4 == 3 else np.uint8
        top = np.iinfo(dtype).max
        image = rng.integers(0, top + 1, (h, w)).astype(dtype)
        image[rng.random((h, w)) < 0.1] = top
        image[rng.random((h, w)) < 0.1] = 0
        if trial % 2:
            image.setflags(write=False)
        pixels = rng.choice(h * w, int(rng.integers(1, h * w + 1)), replace=False).astype(np.int64)
        scale = 40.0 if trial % 5 == 0 else 1.0
        log_d, delta = rng.normal(0, scale, pixels.size), rng.normal(0, scale, pixels.size)
        divisor = (pixels, log_d, None if trial % 3 == 2 else delta)
        aps = edi.ApsResponse(black_level=12.0 if dtype == np.uint8 and trial % 2 else 0.0,
                              gamma=2.2 if trial % 3 == 1 else 1.0)
        state = LatentState(w, h)
        if reference:
            with edi.numpy_reference():
                deblurred, _ = state.set_reference(image, aps, divisor, (0.3, 0.3), step)
        else:
            deblurred, _ = state.set_reference(image, aps, divisor, (0.3, 0.3), step)
        own, shown, lat = _brute_start(image, aps, divisor, step)
        np.testing.assert_allclose(state.log_ref, own, atol=1e-5)
        np.testing.assert_allclose(state.log_lat, lat, atol=1e-5)
        assert np.abs(deblurred.astype(int) - edi.to_uint8(shown.astype(np.float32)).astype(int)).max() <= 1


def test_a_mosaic_is_not_smoothed():
    """A colour camera's Bayer mosaic keeps per-pixel EDI (its same-colour footprint is 5x5 px): with the switch on
    or off, the same deblurred and latent images, and the lone event's pixel stays brightened."""
    frame, ev = _still_frame_with_one_event()
    frame = dataclasses.replace(frame, color_filter="RGGB")
    outs = []
    for median in (True, False):
        rec = EdiReconstructor(24, 18, c=0.3, divisor_median=median, black_level=0.0, clock_offset_us=0)
        out = rec.on_frame(frame, ev)
        outs.append((out.image.copy(), rec.render().image.copy(), rec.reference_log()[0].copy()))
    for a, b in zip(*outs):
        assert np.array_equal(a, b)
    assert outs[0][2][5, 7] > np.log(120.0) + 0.02  # the pixel's own correction, not the median's (none)


def test_a_pixel_restarted_after_the_frame_shows_what_the_deblurred_frame_showed():
    """A pixel the flicker detector flags after the frame restarts at L(f): the L(f) the deblurred frame showed
    (the median's), not its own per-pixel correction, which the median had dropped (here a lone event's)."""
    from edi_live.latent_state import LatentState

    image = np.full((6, 8), 120, np.uint8)
    pixels = np.array([2 * 8 + 3], np.int64)
    state = LatentState(8, 6)
    deblurred, _ = state.set_reference(image, edi.ApsResponse(), (pixels, np.array([-0.3]), np.array([0.0])),
                                       (0.3, 0.3), 1)
    state.restart_pixels(pixels)
    assert state.display[2, 3] == deblurred[2, 3]


def test_the_frame_finish_refuses_what_it_cannot_render():
    """Without the f -> te exponent there is no latent image at te to write, and a shown divisor needs an array for
    the L(f) it shows: both are refused in one line instead of a kernel crash or a silently wrong reference."""
    image = np.full((4, 5), 100, np.uint8)
    pix, zeros = np.arange(3, dtype=np.int64), np.zeros(3)
    arrays = [np.empty((4, 5), t) for t in (np.float32, np.uint8, np.float32, np.uint8)]
    with pytest.raises(ValueError, match="f -> te exponent"):
        edi.finish_frame_u8(image, 255.0, (pix, zeros, None), *arrays)
    with pytest.raises(ValueError, match="log_shown"):
        edi.finish_frame_u8(image, 255.0, (pix, zeros, zeros), *arrays, shown=(zeros, zeros))


@pytest.mark.parametrize("reference", [False, True])
def test_the_frame_finish_refuses_a_shown_divisor_written_over_the_reference(reference):
    """log_shown may be log_ref itself only for per-pixel EDI. With a smoothed divisor shown into log_ref, the
    compiled pass left the median's L(f) in log_ref (which the unreliable-pixel test and nearest/fused read as each
    pixel's own) while the numpy reference kept each pixel's own and showed that: the two disagreed silently."""
    image = np.full((4, 5), 100, np.uint8)
    pix = np.arange(3, dtype=np.int64)
    own, shown = np.array([0.5, -0.5, 0.2]), np.zeros(3)
    log_ref = np.empty((4, 5), np.float32)
    arrays = [log_ref, np.empty((4, 5), np.uint8), np.empty((4, 5), np.float32), np.empty((4, 5), np.uint8)]
    with contextlib.ExitStack() as stack:
        if reference:
            stack.enter_context(edi.numpy_reference())
        with pytest.raises(ValueError, match="log_shown"):
            edi.finish_frame_u8(image, 255.0, (pix, own, shown), *arrays, shown=(shown, shown), log_shown=log_ref)

