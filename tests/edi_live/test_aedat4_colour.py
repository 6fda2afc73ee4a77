"""Colour in AEDAT4: raw Bayer frame streams recognised from their metadata (as dv-processing writes it), and our
colour frames and mosaic metadata read back by dv-processing and the `aedat` package as colour."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.aedat4 import Aedat4Reader, Aedat4Writer
from edi_live.aedat4.header import color_filter_of_metadata
from edi_live.datatypes import Frame

T0 = 1_700_000_000_000_000


@pytest.mark.parametrize("value, pattern", [("RGGB", "RGGB"), ("gbrg", "GBRG"), ("RGBG", "RGGB"), ("GRGB", "GRBG"),
                                            ("GBGR", "GBRG"), ("BGRG", "BGGR"), ("4", "BGGR"), ("0", None),
                                            ("MONO", None), ("RGBW", None), ("", None), (None, None)])
def test_colour_filter_metadata_values(value, pattern):
    # our names, libcaer's clockwise names and libcaer's codes; anything else (white filters, mono) is mono
    assert color_filter_of_metadata(value) == pattern


def test_raw_bayer_stream_written_by_dv_processing_is_recognised(tmp_path, rng):
    import dv_processing as dv

    path = tmp_path / "bayer.aedat4"
    cfg = dv.io.MonoCameraWriter.Config("DAVIS346_00000042")
    cfg.addEventStream((346, 260))
    cfg.addFrameStream((346, 260))
    cfg.addStreamMetadata("frames", ("colorFilter", "BGRG"))  # libcaer's name, i.e. our BGGR
    raw = rng.integers(0, 256, (260, 346), dtype=np.uint8)
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    writer.writeFrame(dv.Frame(T0, 1000, 0, 0, raw, dv.FrameSource.SENSOR), "frames")
    del writer
    with Aedat4Reader(path) as reader:
        assert reader.source_info.color_filter == "BGGR" and reader.source_info.is_color
        (frame,) = [data for _, data in reader]
    assert frame.color_filter == "BGGR" and np.array_equal(frame.image, raw)


def test_replay_delivers_the_files_pattern_and_colour_frames(tmp_path, rng):
    from drivers.replay import ReplaySource
    from edi_live.datatypes import EVENT_DTYPE

    events = np.zeros(10, EVENT_DTYPE)
    events["t"] = T0 + 1000 * np.arange(10)
    for pattern, image in (("GRBG", rng.integers(0, 256, (12, 16), dtype=np.uint8)),
                           (None, rng.integers(0, 256, (12, 16, 3), dtype=np.uint8))):
        path = tmp_path / f"{pattern}.aedat4"
        with Aedat4Writer(path, 16, 12, color_filter=pattern) as w:
            w.write_events(events)
            w.write_frame(Frame(image, T0 + 1000, T0 + 2000))
        with ReplaySource(path, speed=0) as src:  # through the decoding child process
            frames = [f for p in src if p is not None for f in p.frames]
        assert src.info.color_filter == pattern
        assert [f.color_filter for f in frames] == [pattern] and np.array_equal(frames[0].image, image)


def test_our_colour_frames_and_mosaic_metadata_read_as_colour_by_dv_processing_and_aedat(tmp_path, rng):
    import aedat
    import dv_processing as dv

    bgr = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    path = tmp_path / "colour.aedat4"
    with Aedat4Writer(path, 16, 12, events=False, color_filter="RGGB") as w:
        w.write_frame(Frame(bgr, T0, T0 + 900))
    rec = dv.io.MonoCameraRecording(str(path))
    frame = rec.getNextFrame()
    assert frame.image.shape == (12, 16, 3) and np.array_equal(frame.image, bgr)
    assert rec.getStreamMetadataValue("frames", "colorFilter") == "RGGB"
    (packet,) = list(aedat.Decoder(str(path)))
    assert packet["frame"]["format"] == "RGB"  # the Rust reader hands colour out in RGB order
    assert np.array_equal(packet["frame"]["pixels"], bgr[..., ::-1])
    with Aedat4Reader(path) as reader:
        (again,) = [data for _, data in reader]
    assert np.array_equal(again.image, bgr) and again.color_filter is None  # BGR frames carry no pattern
