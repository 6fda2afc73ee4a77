"""Colour scenes: a Bayer mosaic over an RGB scene; each pixel's events and APS value follow its own channel."""

import numpy as np
import pytest

from edi_live.colour import channel_map, mosaic
from edi_live.simulation import SceneConfig, load_ground_truth, preset, save_ground_truth, simulate


@pytest.fixture(scope="module")
def sim():
    return simulate(SceneConfig(width=64, height=48, duration_s=0.12, color_filter="GRBG", c_sigma=0.0,
                                velocity_px_s=(150.0, 40.0), color_c_scale=(1.25, 1.0, 0.8)))


def test_frames_are_raw_mosaics_and_ground_truth_is_bgr(sim):
    assert all(f.color_filter == "GRBG" and f.image.shape == (48, 64) for f in sim.frames)
    assert sim.gt_images.shape[1:] == (48, 64, 3)
    # the texture is coloured: channels differ clearly somewhere
    gt = sim.gt_images[0]
    assert np.percentile(np.abs(gt[..., 2] - gt[..., 0]), 90) > 10


def test_events_follow_each_pixels_own_channel(sim):
    i, j = 0, int(np.flatnonzero(sim.gt_kind == 0)[-1])
    t0, t1 = sim.gt_t_us[i], sim.gt_t_us[j]
    ev = sim.events[(sim.events["t"] > t0) & (sim.events["t"] <= t1)]
    net = np.zeros((48, 64))
    np.add.at(net, (ev["y"], ev["x"]), np.where(ev["p"], sim.c_on_map[ev["y"], ev["x"]], -sim.c_off_map[ev["y"], ev["x"]]))
    own = np.log(mosaic(sim.gt_images[j], "GRBG")) - np.log(mosaic(sim.gt_images[i], "GRBG"))
    err_own = np.abs(net - own)
    assert np.median(err_own) < 0.25  # within about one threshold (c of 0.16..0.25 here)
    other = np.log(sim.gt_images[j][..., 1]) - np.log(sim.gt_images[i][..., 1])  # green everywhere
    not_green = channel_map("GRBG", 48, 64) != 1
    assert np.median(np.abs(net - other)[not_green]) > np.median(err_own[not_green])


def test_channel_thresholds_are_scaled(sim):
    chan = channel_map("GRBG", 48, 64)
    for c, want in ((0, 0.25), (1, 0.2), (2, 0.16)):
        assert sim.c_on_map[chan == c] == pytest.approx(want, rel=1e-5)


def test_ground_truth_file_keeps_colour(sim, tmp_path):
    save_ground_truth(sim, tmp_path / "gt.npz")
    gt = load_ground_truth(tmp_path / "gt.npz")
    assert gt["config"]["color_filter"] == "GRBG" and gt["gt_images"].shape == sim.gt_images.shape


def test_grey_scene_has_no_colour_fields_and_bad_pattern_is_refused():
    assert preset("colour").color_filter == "RGGB"
    with pytest.raises(ValueError, match="color_filter"):
        simulate(SceneConfig(duration_s=0.05, color_filter="RGBG"))


@pytest.mark.parametrize("pattern", ["RGGB", "GRBG", "GBRG", "BGGR"])
def test_the_simulator_reads_pattern_names_as_the_node_does(pattern):
    from edi_live.simulation.colour_scene import sensor_channels

    assert (sensor_channels(pattern, 5, 7) == channel_map(pattern, 5, 7)).all()


def test_a_written_colour_recording_names_its_pattern(tmp_path):
    from drivers.replay import ReplaySource
    from edi_live.simulation import write_aedat4

    sim = simulate(SceneConfig(width=16, height=12, duration_s=0.06, color_filter="GRBG"))
    write_aedat4(sim, tmp_path / "c.aedat4")
    source = ReplaySource(tmp_path / "c.aedat4")
    try:
        assert source.info.color_filter == "GRBG"  # else a replay would read the mosaic as grey
    finally:
        source.stop()


def test_a_grey_simulations_calibration_is_refused_for_a_colour_one(tmp_path):
    """Calibrations are keyed by camera and size: a colour simulation must not name the grey one's camera."""
    from drivers.replay import ReplaySource
    from edi_live import calibration
    from edi_live.errors import ConfigError
    from edi_live.simulation import write_aedat4

    infos = {}
    for name, pattern in (("grey", None), ("colour", "RGGB")):
        write_aedat4(simulate(SceneConfig(width=16, height=12, duration_s=0.06, color_filter=pattern)),
                     tmp_path / f"{name}.aedat4")
        source = ReplaySource(tmp_path / f"{name}.aedat4")
        try:
            infos[name] = source.info
        finally:
            source.stop()
    grey = calibration.Calibration(infos["grey"].label, 16, 12, 0.2, 0.2)
    grey.check_for(infos["grey"], "grey.json")
    with pytest.raises(ConfigError, match="is for edi-live-sim .*but this camera is edi-live-sim-RGGB"):
        grey.check_for(infos["colour"], "grey.json")
