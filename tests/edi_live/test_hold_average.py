"""hold_average against a float64 numpy sum, exactness on constant images, and the wide-window integer path."""

import numpy as np
import pytest

from edi_live.hold_average import FLOAT32_EXACT_SPAN_US, INT32_SPAN_US, hold_average


def _reference(images, holds, span):
    return sum(im.astype(np.float64) * h for im, h in zip(images, holds)) / span


def test_matches_float64_reference():
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (7, 9), dtype=np.uint8) for _ in range(5)]
    holds = [1000, 3, 2500, 17, 480]
    out = hold_average(images, holds, sum(holds))
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, _reference(images, holds, sum(holds)), rtol=1e-6)


def test_constant_images_average_to_themselves_bit_for_bit():
    image = np.full((4, 5), 201, np.uint8)
    out = hold_average([image, image.copy(), image.copy()], [7, 11, 13], 31)
    assert np.array_equal(out, image.astype(np.float32))


def test_windows_too_long_for_int32_or_float32():
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (3, 3, 3), dtype=np.uint8) for _ in range(2)]
    for span in (FLOAT32_EXACT_SPAN_US + 1, INT32_SPAN_US + 10):
        holds = [span // 3, span - span // 3]
        out = hold_average(images, holds, span)
        assert out.dtype == np.float64 and out.shape == (3, 3, 3)
        np.testing.assert_allclose(out, _reference(images, holds, span), rtol=1e-12)


def test_non_contiguous_images():
    rng = np.random.default_rng(2)
    base = rng.integers(0, 256, (6, 8), dtype=np.uint8)
    view = base[:, ::2]
    out = hold_average([view, view], [1, 3], 4)
    np.testing.assert_array_equal(out, view.astype(np.float32))


def test_holds_longer_than_the_span_do_not_wrap_around():
    image = np.full((2, 2), 255, np.uint8)
    out = hold_average([image], [INT32_SPAN_US + 5], INT32_SPAN_US)  # a sum beyond int32
    np.testing.assert_allclose(out, 255.0 * (INT32_SPAN_US + 5) / INT32_SPAN_US)


def test_no_image_is_an_error_not_an_index_error():
    with pytest.raises(ValueError, match="at least one image"):
        hold_average([], [], 10)
