"""A colour DAVIS346 over USB: the APS colour-filter register read as libcaer reads it, frames tagged with the
pattern, and the colour emulator through the real pyusb paths of the driver, up to the node."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.davis import models
from drivers.davis.device import DavisSource
from drivers.davis.discovery import list_devices
from drivers.emulator import backend, colour_backend
from edi_live.colour import channel_map, mosaic
from edi_live.datatypes import COLOR_FILTERS, Frame, Packet
from tests.helpers.recordings import flatten, random_recording

# libcaer's own pixel-colour table (src/frame_utils.c, determinePixelColor), written out per code as
# {(x % 2, y % 2): colour}: the independent oracle of the code -> pattern mapping.
LIBCAER_PIXEL_COLOURS = {
    1: {(0, 0): "R", (1, 0): "G", (0, 1): "G", (1, 1): "B"},  # RGBG
    2: {(0, 0): "G", (1, 0): "R", (0, 1): "B", (1, 1): "G"},  # GRGB
    3: {(0, 0): "G", (1, 0): "B", (0, 1): "R", (1, 1): "G"},  # GBGR
    4: {(0, 0): "B", (1, 0): "G", (0, 1): "G", (1, 1): "R"},  # BGRG
}


@pytest.mark.parametrize("code", sorted(LIBCAER_PIXEL_COLOURS))
def test_libcaer_filter_codes_give_the_pixel_colours_libcaer_uses(code):
    chan = channel_map(models.color_filter_of_code(code), 2, 2)  # BGR index per pixel
    for (x, y), colour in LIBCAER_PIXEL_COLOURS[code].items():
        assert "BGR"[chan[y, x]] == colour


def test_mono_and_unsupported_filter_codes():
    assert models.color_filter_of_code(0) is None and models.code_of_color_filter(None) == 0
    for code in (5, 8, 42):  # RGBW variants and garbage: a clear refusal, never a wrong pattern
        with pytest.raises(ValueError, match=f"code {code}"):
            models.color_filter_of_code(code)
    assert {models.code_of_color_filter(p) for p in COLOR_FILTERS} == {1, 2, 3, 4}


def _colour_recording(rng, width=346, height=260):
    """A random recording whose APS frames are demosaiced BGR (what the emulated sensor must mosaic)."""
    packets = random_recording(rng, width, height, n_events=3000, n_frames=3, n_imu=0, duration_us=120_000)
    out = []
    for p in packets:
        frames = [Frame(rng.integers(0, 256, (height, width, 3), dtype=np.uint8), f.exposure_start_us,
                        f.exposure_end_us, seq=f.seq) for f in p.frames]
        out.append(Packet(p.events, frames, p.imu, p.triggers, p.watermark_us))
    return out


def _read_all(src: DavisSource, want_frames: int, timeout_s: float = 30) -> list[Packet]:
    got, deadline = [], time.monotonic() + timeout_s
    for p in src:
        if p is not None:
            got.append(p)
        if sum(len(q.frames) for q in got) >= want_frames or time.monotonic() > deadline:
            src.stop()
    return got


def test_colour_emulator_streams_raw_mosaics_tagged_with_the_register_pattern(rng):
    packets = _colour_recording(rng)
    bgr = [f.image for _, frames, _ in [flatten(packets)] for f in frames]
    emu = colour_backend(packets, speed=0, color_filter="GRBG")
    assert emu.regs[(2, 3)] == 2  # APS/COLOR_FILTER answers libcaer's GRGB code
    (listed,) = list_devices(emu)
    assert "colour (GRBG Bayer)" in str(listed)
    with DavisSource(backend=emu, policy="wait") as src:
        got = _read_all(src, 3)
        assert src.info.color_filter == "GRBG" and src.info.is_color
    _, frames, _ = flatten(got)
    assert len(frames) == 3
    for f, original in zip(frames, bgr):
        assert f.color_filter == "GRBG" and f.image.shape == (260, 346)
        np.testing.assert_array_equal(f.image, mosaic(original, "GRBG"))  # through the USB word stream


def test_mono_emulator_reports_mono_and_untagged_frames(rng):
    packets = random_recording(rng, 240, 180, n_events=2000, n_frames=1, n_imu=0, duration_us=100_000)
    emu = backend(packets, speed=0)
    assert str(list_devices(emu)[0]).endswith(" mono")
    with DavisSource(backend=emu, policy="wait") as src:
        got = _read_all(src, 1)
        assert src.info.color_filter is None
    assert [f.color_filter for f in flatten(got)[1]] == [None]


def test_colour_emulator_generated_scene_comes_from_the_simulator():
    with DavisSource(backend=colour_backend(speed=0), policy="wait") as src:
        frames = flatten(_read_all(src, 2))[1]
    assert len(frames) >= 2 and all(f.color_filter == "RGGB" for f in frames)
    # a colour scene seen through the mosaic: the colour planes of the raw frame differ
    chan = channel_map("RGGB", 260, 346)
    img = frames[-1].image.astype(float)
    means = [img[chan == c].mean() for c in range(3)]
    assert max(means) - min(means) > 2.0


def test_node_receives_colour_tagged_frames_and_records_their_pattern(rng, tmp_path):
    from edi_live.aedat4 import Aedat4Reader
    from edi_live.config import NodeConfig
    from edi_live.node import Node
    from tests.edi_live.test_worker import StandIn

    raw = tmp_path / "raw.aedat4"
    stand_in = StandIn()
    cfg = NodeConfig.from_options({"device": "davis346", "no_publish": True, "record": str(raw)})
    src = DavisSource(backend=colour_backend(_colour_recording(rng), speed=0), policy="wait")
    Node(cfg, src, reconstructor_factory=lambda w, h, e: stand_in).run()
    given = [f for f, _ in stand_in.frames_given if f.exposure_start_us > 10**15]  # not the warm-up's frames
    assert given and all(f.color_filter == "RGGB" for f in given)  # (the worker's gates may skip some)
    with Aedat4Reader(raw) as reader:
        assert reader.source_info.color_filter == "RGGB"
        recorded = [data for _, _, data in reader.records(("FRME",))]
    assert [f.color_filter for f in recorded] == ["RGGB"] * 3
    np.testing.assert_array_equal(recorded[0].image, given[0].image)
