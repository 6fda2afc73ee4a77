"""The time average of images each held for a while: what a viewer saw over a window, in exact arithmetic.

Plain functions on numpy arrays. `hold_average` weights each uint8 image by its hold time in µs, sums in integers
(exact: a constant sequence averages to itself bit for bit) and divides once. The multiply-add runs as one
compiled pass per image (numpy needs a product temporary and a second pass: ~4x the time, which made the
prediction figure of edi_live.quality a tenth of the node's CPU on a fast scene).
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np

INT32_SPAN_US = (2**31 - 1) // 255
"""Longest window whose µs-weighted sum of uint8 values fits int32."""
FLOAT32_EXACT_SPAN_US = 2**24 // 255
"""... and whose sums are exact float32 integers (the quotient is then returned as float32)."""


@numba.njit(cache=True, nogil=True)
def _add_scaled(acc: np.ndarray, image: np.ndarray, weight: int) -> None:
    for i in range(acc.size):
        acc[i] += image[i] * weight


def hold_average(images: Sequence[np.ndarray], holds: Sequence[int], span: int) -> np.ndarray:
    """Σ images[j] * holds[j] / span over uint8 images of one shape (holds in µs, summing to `span` > 0 when the
    images cover the window): float32 when exact in it, else float64."""
    if not images or len(holds) != len(images):
        raise ValueError(f"hold_average needs one hold per image and at least one image (got {len(images)} "
                         f"images, {len(holds)} holds)")
    shape = images[0].shape
    acc_type = np.int32 if max(span, sum(holds)) <= INT32_SPAN_US else np.int64  # the sum never wraps
    acc = np.zeros(int(np.prod(shape)), acc_type)
    for image, hold in zip(images, holds):
        _add_scaled(acc, np.ascontiguousarray(image).reshape(-1), acc_type(hold))
    acc = acc.reshape(shape)
    if span <= FLOAT32_EXACT_SPAN_US:
        return np.divide(acc, np.float32(span), dtype=np.float32)
    return acc / float(span)
