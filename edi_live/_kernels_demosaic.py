"""A compiled bilinear Bayer demosaic of 8-bit mosaics, bit-identical to OpenCV's `COLOR_Bayer..2BGR`.

Private to edi_live.colour, which chooses it over OpenCV for uint8 mosaics of at least 3x3 pixels (OpenCV stays
the reference the tests compare it with, and the path for everything else).

Why not OpenCV: a colour node demosaics every latent frame it emits, and on a 346x260 mosaic OpenCV's pass costs
~36 µs of one core, about what a whole grey latent frame of 1000 events costs. Written as one loop over each row
with the interpolation chosen per column by a select (no branch), LLVM vectorises it: ~26 µs.

The arithmetic is OpenCV's: a missing green, or the missing red/blue at a red/blue site, is the mean of 4
neighbours (cross or diagonal) rounded half up, (a + b + c + d + 2) >> 2; a missing red/blue at a green site is
the mean of its 2 same-colour neighbours in the row or the column, (a + b + 1) >> 1. The outermost rows and
columns repeat their inner neighbours.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, boundscheck=False)
def _interior(raw, out, red_in_row0, phase_row0):
    """Rows and columns 1..n-2 of `out` ((h, 3w) uint8 view). Row 0's red or blue pixels (red if red_in_row0)
    sit at columns of parity phase_row0; each row down swaps both."""
    h, w = raw.shape
    for y in range(1, h - 1):
        odd = y & 1
        phase = phase_row0 ^ odd
        red_here = (red_in_row0 ^ odd) == 1
        up = raw[y - 1]
        mid = raw[y]
        dn = raw[y + 1]
        row = out[y]
        for x in range(1, w - 1):
            left = np.uint16(mid[x - 1])
            right = np.uint16(mid[x + 1])
            above = np.uint16(up[x])
            below = np.uint16(dn[x])
            own = np.uint16(mid[x])
            diag = np.uint16(up[x - 1]) + np.uint16(up[x + 1]) + np.uint16(dn[x - 1]) + np.uint16(dn[x + 1])
            site = ((x + phase) & 1) == 0  # this row's red/blue pixel (else green)
            here = own if site else (left + right + 1) >> 1  # the row's own red/blue
            green = (left + right + above + below + 2) >> 2 if site else own
            other = (diag + 2) >> 2 if site else (above + below + 1) >> 1  # the other of red/blue
            row[3 * x] = np.uint8(other if red_here else here)
            row[3 * x + 1] = np.uint8(green)
            row[3 * x + 2] = np.uint8(here if red_here else other)


@njit(cache=True, nogil=True, boundscheck=False)
def _borders(out):
    """Repeat the inner neighbours into the outermost columns, then rows ((h, w, 3) view)."""
    h, w = out.shape[0], out.shape[1]
    for y in range(1, h - 1):
        for k in range(3):
            out[y, 0, k] = out[y, 1, k]
            out[y, w - 1, k] = out[y, w - 2, k]
    out[0] = out[1]
    out[h - 1] = out[h - 2]


def bilinear_u8(raw: np.ndarray, red_in_row0: bool, phase_row0: int) -> np.ndarray:
    """(h, w, 3) BGR of the C-contiguous (h, w) uint8 mosaic, h and w at least 3."""
    h, w = raw.shape
    out = np.empty((h, w, 3), np.uint8)
    _interior(raw, out.reshape(h, 3 * w), int(red_in_row0), int(phase_row0))
    _borders(out)
    return out
