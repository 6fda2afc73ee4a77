"""numba kernel of edi_live.edi.lone: the lone-change test over a whole frame.

Private to edi_live.edi (see lone.py for the contract and the numpy reference).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True)
def _change_signs(log_lat, log_start, width, height, eps, padded):
    """padded[(y + 1) * (width + 2) + x + 1] = the sign of pixel (x, y)'s log change beyond eps (not the border)."""
    pw = width + 2
    for y in range(height):
        row = y * width
        p = padded[(y + 1) * pw + 1:(y + 1) * pw + 1 + width]
        for x in range(width):
            d = log_lat[row + x] - log_start[row + x]
            p[x] = np.int8(d > eps) - np.int8(d < -eps)


@njit(cache=True, nogil=True, fastmath=True)
def _lone_rows(padded, width, height, need, lone):
    """lone[y * width + x] = 1 where pixel (x, y) changed and fewer than `need` of its 8 neighbours changed the same
    way (the padded border counts as unchanged); row by row on contiguous views, branch-free (~0.6 ns a pixel)."""
    pw = width + 2
    for y in range(height):
        a = padded[y * pw:y * pw + pw]
        b = padded[(y + 1) * pw:(y + 1) * pw + pw]
        c = padded[(y + 2) * pw:(y + 2) * pw + pw]
        o = lone[y * width:y * width + width]
        for x in range(width):
            s = b[x + 1]
            same = (np.int8(a[x] == s) + np.int8(a[x + 1] == s) + np.int8(a[x + 2] == s) + np.int8(b[x] == s)
                    + np.int8(b[x + 2] == s) + np.int8(c[x] == s) + np.int8(c[x + 1] == s) + np.int8(c[x + 2] == s))
            o[x] = np.int8(s != 0) & np.int8(same < need)


@njit(cache=True, nogil=True)
def lone_changes_u8(log_lat, log_start, display, start_display, width, height, need, eps, padded, lone, out):
    """out = display, except at a pixel whose log changed by more than eps since log_start while fewer than `need`
    of its 8 neighbours (on the sensor) changed in the same direction: there start_display. Work arrays, whatever
    they hold: `padded` int8 ((height + 2) * (width + 2)) and `lone` int8 (width * height rounded up to a multiple
    of 8). Their border and tail are zeroed here, not trusted: a scratch of the same length may have served the
    transposed size, whose signs lie on this size's border (and a stale verdict past the last pixel would be
    written past `out`). Two branch-free passes over the pixels, then a copy with rare exceptions."""
    pw = width + 2
    padded[:pw] = 0
    padded[(height + 1) * pw:(height + 2) * pw] = 0
    for y in range(1, height + 1):
        padded[y * pw] = 0
        padded[y * pw + pw - 1] = 0
    lone[width * height:] = 0
    _change_signs(log_lat, log_start, width, height, eps, padded)
    _lone_rows(padded, width, height, need, lone)
    out[:] = display
    words = lone.view(np.uint64)  # lone pixels are few: skip eight verdicts at a time
    for k in range(words.size):
        if words[k] != 0:
            for i in range(8 * k, 8 * k + 8):
                if lone[i]:
                    out[i] = start_display[i]

