"""Picking events out of a time-ordered batch: time windows by binary search, pixel selection, ON/OFF counts.

Times are int64 µs; windows are closed, t0 <= t <= t1 (see the package docstring for the exposure convention).
"""

from __future__ import annotations

import bisect

import numpy as np

from edi_live.datatypes import EVENT_DTYPE
from edi_live.edi import _backend, _kernels_pixels, _kernels_stream


def flat_index(events: np.ndarray, width: int) -> np.ndarray:
    return events["y"].astype(np.int64) * width + events["x"].astype(np.int64)


def _has_event_fields(events: np.ndarray) -> bool:
    names = events.dtype.names or ()
    return all(n in names for n in ("t", "x", "y", "p"))


def window(events: np.ndarray, t0: int | None, t1: int | None) -> np.ndarray:
    """The time-ordered events with t0 <= t <= t1, as a view (binary search, no copy)."""
    if events.dtype != EVENT_DTYPE and not _has_event_fields(events):
        raise TypeError(f"events must be a structured array of EVENT_DTYPE (got {events.dtype})")
    t = events["t"]
    lo = 0 if t0 is None else time_index(t, t0, "left")
    hi = t.size if t1 is None else time_index(t, t1, "right")
    return events[lo:hi]


def time_index(t: np.ndarray, value: int, side: str = "left") -> int:
    """Binary search on the (strided) `events["t"]` view. Unlike np.searchsorted, a key of another dtype (float,
    Python int beyond int64) never makes numpy cast the whole array first."""
    find = bisect.bisect_left if side == "left" else bisect.bisect_right
    return find(t, value)


def select(events: np.ndarray, width: int, height: int, t0: int | None, t1: int | None,
            mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Events with t0 <= t <= t1 (time-ordered input), in bounds and not masked: (flat idx, t, p)."""
    if events.dtype != EVENT_DTYPE and not _has_event_fields(events):
        raise TypeError(f"events must be a structured array of EVENT_DTYPE (got {events.dtype})")
    t = events["t"]
    lo = 0 if t0 is None else time_index(t, t0, "left")
    hi = t.size if t1 is None else time_index(t, t1, "right")
    ev = events[lo:hi]
    x = ev["x"]
    y = ev["y"]
    idx = y.astype(np.int64) * width + x
    keep = (x < width) & (y < height)
    if mask is not None:
        keep &= ~mask.reshape(-1)[np.minimum(idx, width * height - 1)]
    if keep.all():
        return idx, ev["t"], ev["p"]
    return idx[keep], ev["t"][keep], ev["p"][keep]


def events_at_pixels(events: np.ndarray, width: int, height: int, pixels: np.ndarray, t0: int | None = None,
                     t1: int | None = None) -> np.ndarray:
    """The events with t0 <= t <= t1 (time-ordered input) at the pixels marked in `pixels` ((H, W) bool), in
    order: a small copy, so that a per-frame table of a pixel sample costs O(sample events), not O(events)."""
    ev = window(events, t0, t1)
    keep = np.ascontiguousarray(pixels, dtype=bool).reshape(-1)
    if _backend.have_numba():
        return ev[_kernels_pixels.select_pixels(ev["x"], ev["y"], width, height, keep.view(np.uint8))]
    x = ev["x"]
    y = ev["y"]
    inside = (x < width) & (y < height)
    idx = y.astype(np.int64) * width + x
    return ev[inside & keep[np.where(inside, idx, 0)]]


def signed_counts(events: np.ndarray, width: int, height: int, *, t0: int | None = None, t1: int | None = None,
                  mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(n_on, n_off) per pixel as flat int64 arrays for events with t0 <= t <= t1 (time-ordered input)."""
    npix = width * height
    n_on = np.zeros(npix, np.int64)
    n_off = np.zeros(npix, np.int64)
    add_counts(events, width, height, n_on, n_off, t0=t0, t1=t1, mask=mask)
    return n_on, n_off


def add_counts(events: np.ndarray, width: int, height: int, n_on: np.ndarray, n_off: np.ndarray, *,
               t0: int | None = None, t1: int | None = None, mask: np.ndarray | None = None, sign: int = 1,
               floor: bool = False) -> None:
    """In place: n_on/n_off (flat int64) += sign * ON/OFF counts of the events with t0 <= t <= t1; with `floor`,
    counts below 0 are then raised to 0. The kernel floors as it counts (no pass over the image), which is the
    same for counts >= 0 before the call, as `floor` requires."""
    if _backend.have_numba():
        ev = window(events, t0, t1)
        m, use_m = _backend.mask_arg(mask)
        _kernels_stream.count_events(ev["x"], ev["y"], ev["p"], width, height, m, use_m, n_on, n_off, int(sign),
                                     bool(floor))
        return
    idx, _, p = select(events, width, height, t0, t1, mask)
    n_on += sign * np.bincount(idx[p], minlength=n_on.size)
    n_off += sign * np.bincount(idx[~p], minlength=n_off.size)
    if floor:
        np.maximum(n_on, 0, out=n_on)
        np.maximum(n_off, 0, out=n_off)


