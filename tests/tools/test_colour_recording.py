"""tools.colour_recording: a simulated colour scene written by dv-processing (as DV records a colour DAVIS346) reads
back as colour, and the node deblurs the file as well as the simulation it came from."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.colour import demosaic
from edi_live.simulation import SceneConfig, simulate
from tools.colour_recording import cpsnr, deblurred_scores, read_recording, write_with_dv_processing


@pytest.fixture(scope="module")
def sim():
    return simulate(SceneConfig(width=48, height=36, duration_s=0.25, color_filter="GRBG",
                                velocity_px_s=(400.0, 60.0), seed=4))


@pytest.mark.parametrize("raw", [False, True])
def test_a_dv_processing_colour_file_is_read_as_colour_and_deblurred_like_the_simulation(tmp_path, sim, raw):
    path = tmp_path / "colour.aedat4"
    write_with_dv_processing(sim, path, raw=raw)
    frames, events, pattern = read_recording(path)
    assert events.size == sim.events.size and len(frames) == len(sim.frames)
    if raw:
        assert pattern == "GRBG" and all(f.color_filter == "GRBG" and f.image.ndim == 2 for f in frames)
    else:  # DV's colour frames are demosaiced BGR and name no pattern
        assert pattern is None and all(f.image.shape == (36, 48, 3) for f in frames)
    # the file names no pattern when BGR: the node is told the scene's, as a user of a known camera would
    from_file = deblurred_scores(sim, frames, events, "GRBG")
    in_memory = deblurred_scores(sim, sim.frames, sim.events, "GRBG")
    blurry = [cpsnr(demosaic(f.image, "GRBG"), sim.gt_at(f.mid_exposure_us)) for f in sim.frames]
    assert np.mean(from_file) > np.mean(blurry) + 3  # deblurring helps on this moving scene
    assert abs(np.mean(from_file) - np.mean(in_memory)) < 0.2  # and the file path loses (almost) nothing


def test_a_mosaic_stored_without_its_pattern_reads_as_grey_frames_of_the_same_values(tmp_path, sim):
    """What bench_colour --node compares: one file, read as grey, or as colour once the pattern is named."""
    path = tmp_path / "mosaic.aedat4"
    write_with_dv_processing(sim, path, raw=True, name_pattern=False)
    frames, events, pattern = read_recording(path)
    assert pattern is None and events.size == sim.events.size
    assert all(f.color_filter is None and np.array_equal(f.image, s.image) for f, s in zip(frames, sim.frames))
