"""Bayer pattern bookkeeping: each pattern's channel map, and mosaic -> demosaic of flat and graded colour fields."""

import numpy as np
import pytest

from edi_live.colour import channel_map, check_pattern, demosaic, mosaic
from edi_live.datatypes import COLOR_FILTERS, Frame


@pytest.mark.parametrize("pattern", COLOR_FILTERS)
def test_channel_map_reads_the_pattern_letters_row_by_row(pattern):
    chan = channel_map(pattern, 4, 6)
    letters = {0: "B", 1: "G", 2: "R"}
    assert "".join(letters[int(v)] for v in (chan[0, 0], chan[0, 1], chan[1, 0], chan[1, 1])) == pattern
    assert (chan[2:, :] == chan[:2, :]).all() and (chan[:, 2:4] == chan[:, :2]).all()


@pytest.mark.parametrize("pattern", COLOR_FILTERS)
def test_a_flat_colour_field_survives_mosaic_and_demosaic(pattern):
    bgr = np.empty((12, 14, 3), np.uint8)
    bgr[...] = (25, 140, 230)
    out = demosaic(mosaic(bgr, pattern), pattern)
    # the interior, away from OpenCV's border handling, is exactly the field
    assert (out[2:-2, 2:-2] == bgr[2:-2, 2:-2]).all()


def test_mosaic_keeps_only_each_pixels_own_channel():
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
    raw = mosaic(bgr, "RGGB")
    assert raw[0, 0] == bgr[0, 0, 2] and raw[0, 1] == bgr[0, 1, 1] and raw[1, 1] == bgr[1, 1, 0]


def test_unknown_patterns_and_colour_frames_are_refused_clearly():
    with pytest.raises(ValueError, match="known: RGGB"):
        check_pattern("RGBW")
    with pytest.raises(ValueError, match="raw 2-D mosaic"):
        Frame(np.zeros((4, 4, 3), np.uint8), 0, 10, color_filter="RGGB")
    assert Frame(np.zeros((4, 4, 3), np.uint8), 0, 10).image.ndim == 3


@pytest.mark.parametrize("pattern", COLOR_FILTERS)
def test_mosaic_to_gray_gives_the_luma_of_a_flat_colour_field(pattern):
    from edi_live.colour import mosaic_to_gray

    bgr = np.empty((12, 14, 3), np.uint8)
    bgr[...] = (25, 140, 230)
    luma = 0.114 * 25 + 0.587 * 140 + 0.299 * 230  # BT.601
    assert np.abs(mosaic_to_gray(mosaic(bgr, pattern), pattern)[2:-2, 2:-2].astype(float) - luma).max() <= 1.0


@pytest.mark.parametrize("method", ["bilinear", "vng", "ea"])
def test_every_demosaicing_method_keeps_a_flat_field(method):
    bgr = np.empty((12, 14, 3), np.uint8)
    bgr[...] = (25, 140, 230)
    out = demosaic(mosaic(bgr, "GBRG"), "GBRG", method)
    assert (out[3:-3, 3:-3] == bgr[3:-3, 3:-3]).all()


def _mosaics():
    """Random, black, white and striped 8-bit mosaics, even and odd sizes down to 3x3, one read-only, one a view."""
    rng = np.random.default_rng(11)
    for h, w in ((3, 3), (3, 4), (4, 3), (5, 7), (11, 13), (12, 14), (180, 240), (260, 346)):
        yield rng.integers(0, 256, (h, w), dtype=np.uint8)
    yield np.zeros((6, 8), np.uint8)
    yield np.full((6, 8), 255, np.uint8)
    yield np.tile(np.array([[0, 255], [255, 0]], np.uint8), (5, 6))  # every rounding at its extreme
    frozen = rng.integers(0, 256, (9, 10), dtype=np.uint8)
    frozen.setflags(write=False)
    yield frozen
    yield rng.integers(0, 256, (10, 24), dtype=np.uint8)[:, ::2]  # not contiguous


@pytest.mark.parametrize("pattern", COLOR_FILTERS)
def test_the_compiled_bilinear_demosaic_is_opencvs_bit_for_bit(pattern):
    from edi_live.edi import numpy_reference

    for raw in _mosaics():
        ours = demosaic(raw, pattern)
        with numpy_reference():  # OpenCV's own conversion
            theirs = demosaic(raw, pattern)
        assert ours.shape == theirs.shape == raw.shape + (3,)
        assert np.array_equal(ours, theirs), (raw.shape, np.argwhere(ours != theirs)[:3])


def test_a_tiny_or_16_bit_mosaic_still_demosaics_through_opencv():
    import cv2

    rng = np.random.default_rng(2)
    raw16 = rng.integers(0, 4096, (6, 8), dtype=np.uint16)
    assert np.array_equal(demosaic(raw16, "RGGB"), cv2.cvtColor(raw16, cv2.COLOR_BayerBG2BGR))
    for shape in ((2, 8), (8, 2), (2, 2)):  # too small for the compiled kernel's 3x3 neighbourhoods
        tiny = rng.integers(0, 256, shape, dtype=np.uint8)
        assert np.array_equal(demosaic(tiny, "RGGB"), cv2.cvtColor(tiny, cv2.COLOR_BayerBG2BGR)), shape
