"""The event helpers of edi_live.datatypes: one dtype out, whatever layout and slicing came in."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.datatypes import EVENT_DTYPE, as_events, concat_events


def _events(rng, n: int, t0: int = 0) -> np.ndarray:
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = t0 + np.sort(rng.integers(0, 1_000_000, n))
    ev["x"], ev["y"] = rng.integers(0, 346, n), rng.integers(0, 260, n)
    ev["p"] = rng.integers(0, 2, n).astype(bool)
    return ev


def _as_rows(ev: np.ndarray) -> list[tuple]:
    return [(int(t), int(x), int(y), bool(p)) for t, x, y, p in zip(ev["t"], ev["x"], ev["y"], ev["p"])]


def test_concat_keeps_every_field_in_order_and_the_exact_dtype(rng):
    parts = [_events(rng, 5), _events(rng, 0), _events(rng, 7, t0=10**6)]
    got = concat_events(parts)
    assert got.dtype == EVENT_DTYPE and got.dtype.itemsize == 16
    assert _as_rows(got) == sum((_as_rows(p) for p in parts), [])


def test_concat_of_strided_and_packed_parts(rng):
    ev = _events(rng, 20)
    packed = np.concatenate([ev[:3], ev[3:6]])  # numpy's own concatenation: a packed 13-byte layout
    assert packed.dtype != EVENT_DTYPE
    got = concat_events([ev[::2], packed])
    assert got.dtype == EVENT_DTYPE
    assert _as_rows(got) == _as_rows(ev[::2]) + _as_rows(ev[:6])


def test_concat_is_a_new_array(rng):
    ev = _events(rng, 4)
    got = concat_events([ev])
    got["t"] += 1
    assert not np.shares_memory(got, ev) and int(ev["t"][0]) == int(got["t"][0]) - 1


def test_concat_of_nothing_is_empty_events():
    got = concat_events([])
    assert got.dtype == EVENT_DTYPE and len(got) == 0


def test_as_events_converts_only_what_needs_it(rng):
    ev = _events(rng, 3)
    assert as_events(ev) is ev
    packed = np.concatenate([ev, ev])
    assert _as_rows(as_events(packed)) == _as_rows(ev) * 2 and as_events(packed).dtype == EVENT_DTYPE
    with pytest.raises(TypeError, match="fields"):
        as_events(np.zeros(3, np.int64))
