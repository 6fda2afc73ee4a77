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


def test_images_of_different_shapes_are_an_error_not_a_read_past_the_end():
    with pytest.raises(ValueError, match="one shape"):
        hold_average([np.full((4, 4), 10, np.uint8), np.full((2, 2), 10, np.uint8)], [1, 1], 2)


@pytest.mark.parametrize("n", [1, 3, 4, 5, 7, 8, 9, 33])
def test_every_group_size_matches_the_integer_reference(n):
    """Four images are added per compiled pass: a short last group (padded with weight-0 images) or a group
    boundary must not drop, repeat or misweight an image. Reference: the exact int64 sum, divided as the
    function documents (float32 when exact in it)."""
    rng = np.random.default_rng(n)
    images = [rng.integers(0, 256, (5, 11), dtype=np.uint8) for _ in range(n)]
    images[0][0, 0] = 255  # extremes at one pixel across every image
    for im in images:
        im[-1, -1] = 0
    holds = [int(h) for h in rng.integers(1, 500, n)]
    span = sum(holds)
    exact = sum(im.astype(np.int64) * h for im, h in zip(images, holds))
    out = hold_average(images, holds, span)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, np.divide(exact, span, dtype=np.float32))


def test_many_images_on_the_int64_path():
    """Past INT32_SPAN_US the sum is int64 (its own compiled signature); more than one group there too."""
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (1, 4), dtype=np.uint8) for _ in range(11)]
    holds = [INT32_SPAN_US // 5] * 11  # the sum is far beyond int32
    span = sum(holds)
    exact = sum(im.astype(np.int64) * h for im, h in zip(images, holds))
    np.testing.assert_array_equal(hold_average(images, holds, span), exact / float(span))


def test_one_pixel_image():
    image = np.array([[255]], np.uint8)
    out = hold_average([image] * 9, [3] * 9, 27)
    assert out.shape == (1, 1) and out[0, 0] == np.float32(255.0)


def test_read_only_images_compile_no_new_signature():
    from edi_live import hold_average as module

    image = np.full((3, 3), 7, np.uint8)
    hold_average([image, image], [1, 1], 2)
    before = set(map(str, module._add_scaled4.signatures))
    frozen = image.copy()
    frozen.setflags(write=False)
    out = hold_average([image, frozen, image], [1, 2, 3], 6)
    np.testing.assert_array_equal(out, image.astype(np.float32))
    assert set(map(str, module._add_scaled4.signatures)) == before
