"""Validation of decoded event records: sorted by time, on the sensor, polarity 0/1, and a time within ±2**62 µs
(the replay keeps 2**62 as "never": a later event would be dropped there without a word).

One pass over the raw 16-byte records in a numba kernel: on DV's small packets (~600 events) a numpy version's
fixed cost of ~6 µs per packet would cut decode throughput by a third. Returns the index of the first bad event
and why, or (-1, 0). `check_events_numpy` is the plain reference the tests check the kernel against.
"""

from __future__ import annotations

import numpy as np
from numba import njit

OK, UNSORTED, OFF_SENSOR, BAD_POLARITY, BAD_TIME = 0, 1, 2, 3, 4
T_LIMIT = 2**62  # |t| must stay below this


def check_events_numpy(raw: np.ndarray, width: int, height: int, t_floor: int) -> tuple[int, int]:
    """The reference for `check_events` (tests only). raw: uint8, C-contiguous, 16 bytes per event record."""
    n = raw.size // 16
    if n == 0:
        return -1, OK
    t = raw.view("<i8")[0::2]
    xy = raw.view("<u2")
    first, why = n, OK
    if t[0] < t_floor or (n > 1 and bool((t[1:] < t[:-1]).any())):
        back = np.concatenate(([t[0] < t_floor], t[1:] < t[:-1]))  # comparisons: a difference could overflow
        first, why = int(np.flatnonzero(back)[0]), UNSORTED
    far = (t >= T_LIMIT) | (t <= -T_LIMIT)
    if bool(far.any()):
        i = int(np.flatnonzero(far)[0])
        first, why = (i, BAD_TIME) if i <= first else (first, why)
    if width and (int(xy[4::8].max()) >= width or int(xy[5::8].max()) >= height):
        i = int(np.flatnonzero((xy[4::8] >= width) | (xy[5::8] >= height))[0])
        first, why = (i, OFF_SENSOR) if i < first else (first, why)
    if int(raw[12::16].max()) > 1:
        i = int(np.flatnonzero(raw[12::16] > 1)[0])
        first, why = (i, BAD_POLARITY) if i < first else (first, why)
    return (first, why) if why else (-1, OK)


@njit(cache=True, nogil=True)
def check_events(raw, width, height, t_floor):  # pragma: no cover - compiled
    """(index of the first bad event, why) or (-1, 0); raw as in check_events_numpy."""
    n = raw.size // 16
    t64 = raw.view(np.int64)
    u16 = raw.view(np.uint16)
    prev = t_floor
    for i in range(n):
        t = t64[2 * i]
        if t < prev:
            return _with_time_fault(t64, i, n, 1)
        prev = t
        if width > 0 and (u16[8 * i + 4] >= width or u16[8 * i + 5] >= height):
            return _with_time_fault(t64, i, n, 2)
        if raw[16 * i + 12] > 1:
            return _with_time_fault(t64, i, n, 3)
    return _with_time_fault(t64, n, n, 0)


@njit(inline="always")
def _with_time_fault(t64, j, n, why):  # pragma: no cover - compiled
    """(first bad event, why) given the first fault `why` found at event j (j = n, why 0: none), events 0..j-1 in
    time order: an event time at or beyond ±T_LIMIT at or before j comes first (as check_events_numpy has it).
    Checked here, not per event: in sorted events only the first and the last before j can be out of range."""
    if n == 0:
        return -1, 0
    if t64[0] >= T_LIMIT or t64[0] <= -T_LIMIT:
        return 0, BAD_TIME
    if j > 0 and t64[2 * (j - 1)] >= T_LIMIT:
        for i in range(j):
            if t64[2 * i] >= T_LIMIT:
                return i, BAD_TIME
    if j < n and (t64[2 * j] >= T_LIMIT or t64[2 * j] <= -T_LIMIT):
        return j, BAD_TIME
    return (j, why) if why else (-1, OK)


@njit(inline="always")
def _u32(b, i):  # pragma: no cover - compiled
    return np.int64(b[i]) | (np.int64(b[i + 1]) << 8) | (np.int64(b[i + 2]) << 16) | (np.int64(b[i + 3]) << 24)


@njit(inline="always")
def _u16(b, i):  # pragma: no cover - compiled
    return np.int64(b[i]) | (np.int64(b[i + 1]) << 8)


@njit(cache=True, nogil=True)
def parse_check_evts(b, width, height):  # pragma: no cover - compiled
    """An EVTS payload's vtable walk and the event check in one call: (start, count, first bad, why).

    start = -1 means "not the plain layout": the caller falls back to the general (Python) parser, which also
    produces the precise error. Saves ~3 µs of Python per packet, a sixth of the time on DV's small packets.
    """
    n = b.size
    if n < 16 or b[8] != 69 or b[9] != 86 or b[10] != 84 or b[11] != 83:  # "EVTS"
        return -1, 0, -1, 0
    if _u32(b, 0) + 4 > n:
        return -1, 0, -1, 0
    table = _u32(b, 4) + 4
    if table + 4 > n:
        return -1, 0, -1, 0
    so = _u32(b, table)
    if so >= 2**31:
        so -= 2**32
    vt = table - so
    if vt < 0 or vt + 6 > n:
        return -1, 0, -1, 0
    off = _u16(b, vt + 4)
    if _u16(b, vt) < 6 or off == 0 or table + off + 4 > n:
        return -1, 0, -1, 0
    field = table + off
    v = field + _u32(b, field)
    if v + 4 > n:
        return -1, 0, -1, 0
    count = _u32(b, v)
    start = v + 4
    if start + 16 * count > n or start % 8 != 0:
        return -1, 0, -1, 0
    recs = b[start:start + 16 * count]
    t64 = recs.view(np.int64)
    u16 = recs.view(np.uint16)
    prev = -(2**62)
    for i in range(count):
        t = t64[2 * i]
        if t < prev:
            return (start, count, *_with_time_fault(t64, i, count, 1))
        prev = t
        if width > 0 and (u16[8 * i + 4] >= width or u16[8 * i + 5] >= height):
            return (start, count, *_with_time_fault(t64, i, count, 2))
        if recs[16 * i + 12] > 1:
            return (start, count, *_with_time_fault(t64, i, count, 3))
    return (start, count, *_with_time_fault(t64, count, count, 0))
