"""edi.rows_of (edi/levels.py): which asked pixels a level table holds, in which row, and their level spread,
on both backends against a dictionary of the table's pixels."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE
from tests.edi_live.test_edi import backend, random_events  # noqa: F401 - the backend fixture


@pytest.mark.parametrize("seed", range(4))
def test_rows_of_finds_the_active_pixels_and_their_level_spread(backend, seed):
    """rows_of against a dictionary of the table's pixels: which of the asked pixels are active, in which row, and
    the number of levels - 1 added to `spread` there (and nowhere else); odd seeds ask some pixels twice."""
    rng = np.random.default_rng(seed)
    ev = random_events(rng, 600, 20, 10, 0, 5000)
    table = edi.build_level_table(ev, 20, 10, 0, 5000)
    asked = np.sort(rng.choice(200, size=int(rng.integers(0, 120)), replace=bool(seed % 2))).astype(np.int64)
    spread = np.full(asked.size, 0.5)
    rows, at = edi.rows_of(table, asked, spread)
    row_of = {int(q): r for r, q in enumerate(table.pixels)}
    want_at = [i for i, q in enumerate(asked) if int(q) in row_of]
    np.testing.assert_array_equal(at, want_at)
    np.testing.assert_array_equal(rows, [row_of[int(asked[i])] for i in want_at])
    want_spread = np.full(asked.size, 0.5)
    for i in want_at:
        r = row_of[int(asked[i])]
        want_spread[i] += table.lvl_start[r + 1] - table.lvl_start[r] - 1
    np.testing.assert_array_equal(spread, want_spread)


def test_rows_of_a_pixel_asked_twice_matches_its_row_twice(backend):
    """More matches than the table has rows: one slot per asked pixel, as the numpy path gives."""
    ev = np.zeros(2, EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"], ev["p"] = 3, 2, [100, 200], True
    table = edi.build_level_table(ev, 20, 10, 0, 5000)
    q = 2 * 20 + 3
    spread = np.zeros(3)
    rows, at = edi.rows_of(table, np.array([q, q, q]), spread)
    np.testing.assert_array_equal(at, [0, 1, 2])
    np.testing.assert_array_equal(rows, [0, 0, 0])


def test_rows_of_an_empty_table_finds_nothing(backend):
    table = edi.build_level_table(np.zeros(0, EVENT_DTYPE), 20, 10, 0, 5000)
    spread = np.zeros(3)
    rows, at = edi.rows_of(table, np.array([1, 5, 7]), spread)
    assert rows.size == 0 and at.size == 0 and not spread.any()
