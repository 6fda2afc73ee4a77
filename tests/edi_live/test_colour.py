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
