"""Validation of decoded event records: sorted by time, on the sensor, polarity 0/1.

One pass over the raw 16-byte records. With numba (optional) it is a compiled loop: on DV's small packets
(~600 events) the numpy version's fixed cost of ~6 µs per packet would cut decode throughput by a third
(tools/bench_aedat4.py measures both). Returns the index of the first bad event and why, or (-1, 0).
"""

from __future__ import annotations

import numpy as np

OK, UNSORTED, OFF_SENSOR, BAD_POLARITY = 0, 1, 2, 3


def check_events_numpy(raw: np.ndarray, width: int, height: int, t_floor: int) -> tuple[int, int]:
    """raw: uint8, C-contiguous, 16 bytes per event record. Cheap whole-array tests first; indices only on failure."""
    n = raw.size // 16
    if n == 0:
        return -1, OK
    t = raw.view("<i8")[0::2]
    xy = raw.view("<u2")
    first, why = n, OK
    if t[0] < t_floor or (n > 1 and bool((t[1:] < t[:-1]).any())):
        first, why = int(np.flatnonzero(np.diff(t, prepend=np.int64(t_floor)) < 0)[0]), UNSORTED
    if width and (int(xy[4::8].max()) >= width or int(xy[5::8].max()) >= height):
        i = int(np.flatnonzero((xy[4::8] >= width) | (xy[5::8] >= height))[0])
        first, why = (i, OFF_SENSOR) if i < first else (first, why)
    if int(raw[12::16].max()) > 1:
        i = int(np.flatnonzero(raw[12::16] > 1)[0])
        first, why = (i, BAD_POLARITY) if i < first else (first, why)
    return (first, why) if why else (-1, OK)


try:
    from numba import njit

    @njit(cache=True, nogil=True)
    def _check_jit(raw, width, height, t_floor):  # pragma: no cover - compiled
        n = raw.size // 16
        t64 = raw.view(np.int64)
        u16 = raw.view(np.uint16)
        prev = t_floor
        for i in range(n):
            t = t64[2 * i]
            if t < prev:
                return i, 1
            prev = t
            if width > 0 and (u16[8 * i + 4] >= width or u16[8 * i + 5] >= height):
                return i, 2
            if raw[16 * i + 12] > 1:
                return i, 3
        return -1, 0

    check_events = _check_jit

    HAVE_NUMBA = True
except ImportError:  # numba is optional: same contract, numpy speed
    check_events = check_events_numpy
    HAVE_NUMBA = False
