"""Bayer mosaics: which colour each pixel of a colour DAVIS sees, and conversion between mosaic and BGR images.

Plain functions on numpy arrays (no state). A pattern is a `datatypes.ColorFilter`, named by its top-left 2x2 block
read row by row. Channel indices follow OpenCV's BGR order: 0 = blue, 1 = green, 2 = red.
"""

from __future__ import annotations

import cv2
import numpy as np

from edi_live._kernels_demosaic import bilinear_u8
from edi_live.datatypes import COLOR_FILTERS, ColorFilter
from edi_live.edi import have_numba

_LETTER_TO_CHANNEL = {"B": 0, "G": 1, "R": 2}

# OpenCV names its Bayer conversions after the second row's second and third pixels, which is the top-left
# block's bottom-right and the next column: a sensor whose top-left block is RGGB uses COLOR_BayerBG2BGR.
_TO_BGR = {
    "RGGB": cv2.COLOR_BayerBG2BGR,
    "BGGR": cv2.COLOR_BayerRG2BGR,
    "GRBG": cv2.COLOR_BayerGB2BGR,
    "GBRG": cv2.COLOR_BayerGR2BGR,
}


def check_pattern(pattern: str) -> ColorFilter:
    """`pattern` as a ColorFilter, or ValueError naming the known ones."""
    if pattern not in COLOR_FILTERS:
        raise ValueError(f"unknown Bayer pattern {pattern!r} (known: {', '.join(COLOR_FILTERS)})")
    return pattern  # type: ignore[return-value]


def channel_of_block(pattern: ColorFilter) -> np.ndarray:
    """(2, 2) int array: the BGR channel index of each position of the pattern's 2x2 block."""
    letters = check_pattern(pattern)
    return np.array([[_LETTER_TO_CHANNEL[letters[0]], _LETTER_TO_CHANNEL[letters[1]]],
                     [_LETTER_TO_CHANNEL[letters[2]], _LETTER_TO_CHANNEL[letters[3]]]], dtype=np.int8)


def channel_map(pattern: ColorFilter, height: int, width: int) -> np.ndarray:
    """(height, width) int8: the BGR channel index each pixel of the mosaic sees."""
    block = channel_of_block(pattern)
    return np.tile(block, ((height + 1) // 2, (width + 1) // 2))[:height, :width]


def mosaic(bgr: np.ndarray, pattern: ColorFilter) -> np.ndarray:
    """The raw mosaic a sensor with `pattern` would read of the (h, w, 3) BGR image (same dtype)."""
    if bgr.ndim != 3 or bgr.shape[2] != 3:
        raise ValueError(f"mosaic needs an (h, w, 3) BGR image (got shape {bgr.shape})")
    chan = channel_map(pattern, bgr.shape[0], bgr.shape[1])
    return np.take_along_axis(bgr, chan[..., None].astype(np.intp), axis=2)[..., 0].copy()


# OpenCV's other demosaicing methods, by the same shifted names: variable number of gradients, edge-aware
_VNG = {"RGGB": cv2.COLOR_BayerBG2BGR_VNG, "BGGR": cv2.COLOR_BayerRG2BGR_VNG,
        "GRBG": cv2.COLOR_BayerGB2BGR_VNG, "GBRG": cv2.COLOR_BayerGR2BGR_VNG}
_EA = {"RGGB": cv2.COLOR_BayerBG2BGR_EA, "BGGR": cv2.COLOR_BayerRG2BGR_EA,
       "GRBG": cv2.COLOR_BayerGB2BGR_EA, "GBRG": cv2.COLOR_BayerGR2BGR_EA}
_GRAY = {"RGGB": cv2.COLOR_BayerBG2GRAY, "BGGR": cv2.COLOR_BayerRG2GRAY,
         "GRBG": cv2.COLOR_BayerGB2GRAY, "GBRG": cv2.COLOR_BayerGR2GRAY}
DEMOSAIC_METHODS = {"bilinear": _TO_BGR, "vng": _VNG, "ea": _EA}
DEFAULT_DEMOSAIC = "bilinear"  # as good as "ea" by CPSNR on the simulator, and the cheapest (docs/colour.md)


def demosaic(raw: np.ndarray, pattern: ColorFilter, method: str = "bilinear") -> np.ndarray:
    """(h, w, 3) BGR of the raw (h, w) uint8/uint16 mosaic by one of OpenCV's Bayer interpolations
    (DEMOSAIC_METHODS: "bilinear", "vng" (uint8 only), "ea" edge-aware). Bilinear on uint8 runs a compiled copy of
    OpenCV's (bit-identical, ~0.7x its CPU; _kernels_demosaic) unless inside edi.numpy_reference()."""
    if raw.ndim != 2:
        raise ValueError(f"demosaic needs a 2-D raw mosaic (got shape {raw.shape})")
    if method not in DEMOSAIC_METHODS:
        raise ValueError(f"unknown demosaicing method {method!r} (known: {', '.join(DEMOSAIC_METHODS)})")
    pattern = check_pattern(pattern)
    raw = np.ascontiguousarray(raw)
    if method == "bilinear" and raw.dtype == np.uint8 and min(raw.shape) >= 3 and have_numba():
        red_in_row0 = "R" in pattern[:2]
        return bilinear_u8(raw, red_in_row0, pattern.index("R" if red_in_row0 else "B"))
    return cv2.cvtColor(raw, DEMOSAIC_METHODS[method][pattern])


def one_opencv_thread() -> None:
    """Run OpenCV's conversions on the calling thread only. Its pool would spread each ~35 µs demosaic over cores
    the node's other threads already use: the same wall time at twice the CPU (70 against 37 µs on 2 cores)."""
    cv2.setNumThreads(1)


def mosaic_to_gray(raw: np.ndarray, pattern: ColorFilter) -> np.ndarray:
    """(h, w) grey (BT.601 luma) of the raw mosaic in one OpenCV pass: the same quality as bilinear demosaicing
    then BGR -> grey, at half its cost (docs/colour.md)."""
    if raw.ndim != 2:
        raise ValueError(f"mosaic_to_gray needs a 2-D raw mosaic (got shape {raw.shape})")
    return cv2.cvtColor(np.ascontiguousarray(raw), _GRAY[check_pattern(pattern)])
