"""edi.pair_candidates (edi_live/edi/pairs.py): the compiled pass against its numpy form on random frames."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.edi.pairs import pair_candidates


@pytest.mark.parametrize("masked", [False, True])
def test_the_candidates_are_those_of_the_numpy_form(masked):
    rng = np.random.default_rng(4)
    npix = 50 * 40
    b_prev = rng.uniform(0, 255, npix).astype(np.float32)
    b_cur = rng.uniform(0, 255, npix).astype(np.float32)
    b_prev[:5] = [2.0, 250.0, np.nan, 1.999, 250.001]  # both bounds are in, NaN is out
    inf_prev, inf_cur = rng.random(npix) < 0.9, rng.random(npix) < 0.9
    mask = (rng.random(npix) < 0.1) if masked else None
    n_on = rng.poisson(0.4, npix).astype(np.int64)
    n_off = rng.poisson(0.4, npix).astype(np.int64)
    prev_pixels = np.unique(rng.integers(0, npix, 300))
    cur_pixels = np.unique(rng.integers(0, npix, 300))
    args = (inf_prev, inf_cur, b_prev, b_cur, 2.0, 250.0, mask, n_on, n_off, prev_pixels, cur_pixels)
    got = pair_candidates(*args)
    with edi.numpy_reference():
        want = pair_candidates(*args)
    np.testing.assert_array_equal(got, want)
    assert 0 < got.size < npix
