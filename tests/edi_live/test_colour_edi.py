"""Colour EDI: c per Bayer channel, no mosaic pattern in the output, BGR input re-mosaiced, grey on request."""

import numpy as np
import pytest

from edi_live.colour import channel_map, mosaic
from edi_live.colour_edi import ColourPlan, channel_contrast
from edi_live.contrast import EnergyContrast
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate

W, H = 120, 90


def _run(sim, **knobs) -> tuple[EdiReconstructor, list]:
    rec = EdiReconstructor(W, H, **knobs)
    ev, prev, out = sim.events, None, []
    for f in sim.frames:
        lo = -1 if prev is None else prev
        out.append(rec.on_frame(f, ev[(ev["t"] > lo) & (ev["t"] <= f.exposure_end_us)]))
        prev = f.exposure_end_us
    return rec, out


@pytest.mark.parametrize("scale", [(1.25, 1.0, 0.8), (1.0, 1.0, 1.0)])
def test_a_colour_scene_recovers_its_c_per_channel(scale):
    sim = simulate(SceneConfig(width=W, height=H, duration_s=0.35, color_filter="RGGB", c_sigma=0.0,
                               velocity_px_s=(250.0, 60.0), color_c_scale=scale))
    rec, _ = _run(sim, color_filter="RGGB", history_pairs=4, sample_pixels=W * H)
    got = channel_contrast(rec.estimator, rec.pairs, "RGGB", H, W, (rec.c_on, rec.c_off))
    for name, factor in zip("BGR", scale):
        c_on, c_off = got["channels"][name]
        assert c_on == pytest.approx(0.2 * factor, abs=0.03) and c_off == pytest.approx(0.2 * factor, abs=0.03)
    # per-channel c is chosen exactly when the channels differ
    assert got["per_channel"] == (scale != (1.0, 1.0, 1.0))


def _nyquist_share(img: np.ndarray) -> float:
    """The FFT magnitude at the mosaic's Nyquist frequencies relative to the mean (DC)."""
    spec = np.abs(np.fft.fft2(img.astype(np.float64)))
    h, w = img.shape
    return float(max(spec[h // 2, 0], spec[0, w // 2], spec[h // 2, w // 2]) / spec[0, 0])


def test_a_flat_colour_field_has_no_mosaic_pattern_in_deblurred_and_latent_frames():
    bgr = np.empty((H, W, 3), np.uint8)
    bgr[...] = (40, 120, 200)
    frame = Frame(mosaic(bgr, "GRBG"), 1_000, 11_000, color_filter="GRBG")
    ev = np.zeros(W * H, EVENT_DTYPE)  # every pixel: one ON event after the exposure (a uniform brightening)
    yy, xx = np.divmod(np.arange(W * H), W)
    ev["x"], ev["y"], ev["t"], ev["p"] = xx, yy, 12_000 + np.arange(W * H) // 100, True
    rec = EdiReconstructor(W, H, c=0.2)  # no color_filter configured: the frame's own pattern is used
    deblurred = rec.on_frame(frame, ev[:0]).image
    rec.on_events(ev)
    latent = rec.render().image
    for img in (deblurred, latent):
        assert img.shape == (H, W, 3)
        inner = img[2:-2, 2:-2].reshape(-1, 3).astype(float)
        assert inner.std(axis=0).max() < 0.6  # each channel constant
        for ch in range(3):
            assert _nyquist_share(img[..., ch]) < 1e-3
    assert latent[H // 2, W // 2, 2] == pytest.approx(200 * np.exp(0.2), abs=1.5)
    # the check can fail: the same mosaic read as grey carries the checkerboard
    assert _nyquist_share(frame.image) > 0.1


def test_bgr_input_is_remosaiced_with_the_sources_pattern():
    sim = simulate(SceneConfig(width=W, height=H, duration_s=0.2, color_filter="RGGB", c_sigma=0.0,
                               velocity_px_s=(200.0, 50.0)))
    plan = ColourPlan("RGGB", method="bilinear")
    as_bgr = [Frame(plan.output(f.image), f.exposure_start_us, f.exposure_end_us) for f in sim.frames]
    inner = (slice(2, -2), slice(2, -2))  # bilinear demosaicing keeps the sampled values away from the border
    assert (plan.input_mosaic(as_bgr[0].image)[inner] == sim.frames[0].image[inner]).all()
    raw = _run(sim, c=0.2, color_filter="RGGB")[1]
    bgr_sim = type(sim)(**{**sim.__dict__, "frames": as_bgr})
    bgr = _run(bgr_sim, c=0.2, color_filter="RGGB")[1]
    for a, b in zip(raw, bgr):
        assert b.image.shape == (H, W, 3)
        assert (a.image[4:-4, 4:-4] == b.image[4:-4, 4:-4]).all()
    # a BGR frame from a source that names no pattern: the DAVIS346 colour default, still colour
    unnamed = _run(bgr_sim, c=0.2)[1]
    assert unnamed[-1].image.shape == (H, W, 3)


def test_gray_gives_2d_frames_and_grey_sources_stay_as_they_were():
    sim = simulate(SceneConfig(width=W, height=H, duration_s=0.15, color_filter="BGGR", velocity_px_s=(200.0, 50.0)))
    rec, out = _run(sim, c=0.2, color_filter="BGGR", gray=True)
    rec.on_events(sim.events[-50:])
    assert all(r.image.shape == (H, W) and r.image.dtype == np.uint8 for r in out + [rec.render()])
    grey_sim = simulate(SceneConfig(width=W, height=H, duration_s=0.15, velocity_px_s=(200.0, 50.0)))
    a, b = _run(grey_sim, c=0.2)[1], _run(grey_sim, c=0.2, gray=True)[1]
    assert all(x.image.ndim == 2 and (x.image == y.image).all() for x, y in zip(a, b))


def test_energy_estimator_on_a_mosaic_never_differences_two_channels():
    chan = channel_map("RGGB", 8, 8)
    flat = np.array([50.0, 100.0, 200.0])[chan].astype(np.float32)  # a flat colour field's mosaic
    from edi_live.contrast.energy import _phases, _tv
    assert sum(_tv(p) for p in _phases(flat, True)) == 0.0 and _tv(flat) > 0
    assert EnergyContrast(mosaic=True).mosaic and not EnergyContrast().mosaic
    rec = EdiReconstructor(8, 8, estimator="energy", color_filter="RGGB")
    assert rec.estimator.mosaic


def test_bad_colour_settings_are_config_errors_at_construction():
    from edi_live.errors import ConfigError

    with pytest.raises(ConfigError, match="demosaicing method"):
        EdiReconstructor(W, H, color_filter="RGGB", demosaic="fancy")
    with pytest.raises(ConfigError, match="Bayer pattern"):
        EdiReconstructor(W, H, color_filter="RGBW")
