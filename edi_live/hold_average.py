"""The time average of images each held for a while: what a viewer saw over a window, in exact arithmetic.

Plain functions on numpy arrays. `hold_average` weights each uint8 image by its hold time in µs, sums in integers
(exact: a constant sequence averages to itself bit for bit) and divides once. The multiply-add is compiled and
takes four images per pass over the sum (numpy needs a product temporary and a second pass per image: ~4x the
time, which made the prediction figure of edi_live.quality a tenth of the node's CPU on a fast scene; a pass
per image read and wrote the int32 sum, 4x a uint8 image's bytes, for every image). Integer sums do not depend
on their order, so the grouping changes no bit of the result.
"""

from __future__ import annotations

from typing import Sequence

import numba
import numpy as np

INT32_SPAN_US = (2**31 - 1) // 255
"""Longest window whose µs-weighted sum of uint8 values fits int32."""
FLOAT32_EXACT_SPAN_US = 2**24 // 255
"""... and whose sums are exact float32 integers (the quotient is then returned as float32)."""


GROUP = 4
"""Images added per pass over the sum (1, 2, 4, 8 per pass: 151, 107, 104, 112 µs for 33 frames at 240x180)."""


@numba.njit(cache=True, nogil=True)
def _add_scaled4(acc, i0, w0, i1, w1, i2, w2, i3, w3) -> None:  # noqa: ANN001
    for i in range(acc.size):
        acc[i] += i0[i] * w0 + i1[i] * w1 + i2[i] * w2 + i3[i] * w3


def hold_average(images: Sequence[np.ndarray], holds: Sequence[int], span: int) -> np.ndarray:
    """Σ images[j] * holds[j] / span over uint8 images of one shape (holds in µs, summing to `span` > 0 when the
    images cover the window): float32 when exact in it, else float64."""
    if not images or len(holds) != len(images):
        raise ValueError(f"hold_average needs one hold per image and at least one image (got {len(images)} "
                         f"images, {len(holds)} holds)")
    shape = images[0].shape
    if any(image.shape != shape for image in images):  # the compiled pass would read past the smaller ones
        raise ValueError(f"hold_average needs images of one shape (got {sorted({i.shape for i in images})})")
    acc_type = np.int32 if max(span, sum(holds)) <= INT32_SPAN_US else np.int64  # the sum never wraps
    acc = np.zeros(int(np.prod(shape)), acc_type)
    # a read-only image is copied: numba types read-only arrays apart, and four slots would mean up to 2**4
    # signatures, each compiled mid-stream (the node's emitted frames are writeable)
    flat = [np.ascontiguousarray(image).reshape(-1) for image in images]
    flat = [f if f.flags.writeable else f.copy() for f in flat]
    weights = [acc_type(hold) for hold in holds]
    for k in range(0, len(flat), GROUP):
        args = []
        for j in range(k, k + GROUP):  # a short last group: the first image again, weighted 0
            args += (flat[j], weights[j]) if j < len(flat) else (flat[k], acc_type(0))
        _add_scaled4(acc, *args)
    acc = acc.reshape(shape)
    if span <= FLOAT32_EXACT_SPAN_US:
        return np.divide(acc, np.float32(span), dtype=np.float32)
    return acc / float(span)
