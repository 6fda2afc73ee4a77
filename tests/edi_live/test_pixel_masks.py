"""Which events the reconstructor trusts: hot pixels, the noise filter state, and pixels whose events contradict
the APS frames (UnreliablePixels), judged against hand-built counts and log references."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.pixel_masks import UnreliablePixels


def pair(n_on, n_off, log_prev, log_cur, informative=None):
    n_on, n_off = np.asarray(n_on, np.int64), np.asarray(n_off, np.int64)
    inf = np.ones(len(n_on), bool) if informative is None else np.asarray(informative, bool)
    return n_on, n_off, np.asarray(log_prev, np.float32), np.asarray(log_cur, np.float32), inf, inf


def test_events_that_the_frames_confirm_are_trusted_and_contradicted_ones_are_not():
    u = UnreliablePixels(4, 1)
    c = (0.2, 0.2)
    # pixel 0: +30 ON events (a change of 6 log units) that the frames do not show: a blooming lamp
    # pixel 1: the same events, and the frames show the change: a real brightening
    # pixel 2: balanced flicker, no net change predicted: nothing to contradict
    # pixel 3: two events only: no evidence
    n_on, n_off, lp, lc, ip, ic = pair([30, 30, 40, 2], [0, 0, 40, 0], [3, 3, 3, 3], [3, 9, 3, 3])
    u.update(n_on, n_off, lp, lc, ip, ic, c)
    assert u.mask.reshape(-1).tolist() == [True, False, False, False]
    assert u.count == 1


def test_a_clipped_frame_cannot_confirm_a_huge_change():
    u = UnreliablePixels(2, 1)
    n_on, n_off, lp, lc, _, _ = pair([30, 10], [0, 0], [5, 5], [5, 5])
    clipped = np.array([False, False])
    u.update(n_on, n_off, lp, lc, clipped, clipped, (0.2, 0.2))
    # 6 log units: beyond what a clipped frame may hide; 2 log units: within it
    assert u.mask.reshape(-1).tolist() == [True, False]


def test_a_marked_pixel_is_released_after_the_evidence_fades():
    u = UnreliablePixels(1, 1, decay=0.5, release=0.2)
    bad = pair([30], [0], [3], [3])
    quiet = pair([0], [0], [3], [3])
    u.update(*bad, c=(0.2, 0.2))
    assert u.count == 1
    marked_for = 0
    while u.count and marked_for < 10:
        u.update(*quiet, c=(0.2, 0.2))
        marked_for += 1
    # score 1 halves per quiet pair: 0.5, 0.25, 0.125 < release after three pairs
    assert marked_for == 3


def test_grow_marks_the_halo_around_a_contradicted_pixel():
    u = UnreliablePixels(7, 7, grow_px=2)
    n_on = np.zeros(49, np.int64)
    n_on[3 * 7 + 3] = 30  # the centre pixel's events say x400 brighter; the frames say nothing changed
    zeros = np.zeros(49, np.float32)
    u.update(n_on, np.zeros(49, np.int64), zeros, zeros, np.ones(49, bool), np.ones(49, bool), (0.2, 0.2))
    mask = u.mask
    assert mask[3, 3] and mask[1, 3] and mask[3, 5] and mask[2, 2]  # within 2 px
    assert not mask[0, 0] and not mask[3, 0]  # beyond


def test_a_marked_pixel_that_keeps_firing_stays_marked():
    # while marked, its events are ignored and its counts between frames are 0: only its firing in the exposure
    # (busy) says it is still the flickering lamp; a quiet one is released as its score decays
    u = UnreliablePixels(2, 1, decay=0.5, release=0.2)
    u.update(*pair([30, 30], [0, 0], [3, 3], [3, 3]), c=(0.2, 0.2))
    assert u.mask.reshape(-1).tolist() == [True, True]
    masked_counts = pair([0, 0], [0, 0], [3, 3], [3, 3])
    for _ in range(10):
        u.update(*masked_counts, c=(0.2, 0.2), busy=np.array([12, 0]))
    assert u.mask.reshape(-1).tolist() == [True, False]


@pytest.mark.parametrize("with_busy", [False, True])
def test_contradiction_kernel_equals_the_numpy_reference(with_busy):
    """The compiled unreliable-pixel update gives the numpy reference's scores and marks bit for bit, on pairs
    with clipped frames, held (busy) marked pixels and scores near the release threshold."""
    import edi_live.edi as edi

    rng = np.random.default_rng(3)
    n = 5000
    kw = dict(min_events=3, min_change=2.5, relative=0.9, saturated_limit=4.0, decay=0.8, release=0.2)
    score0 = rng.choice(np.float32([0.0, 0.2, 0.25, 0.9, 1.0, 1.7]), n)
    own0 = rng.random(n) < 0.3
    for _ in range(3):
        n_on, n_off = rng.integers(0, 30, n), rng.integers(0, 30, n)
        log_prev = rng.normal(0, 2, n).astype(np.float32)
        log_cur = (log_prev + rng.normal(0, 3, n)).astype(np.float32)
        inf_prev, inf_cur = rng.random(n) < 0.9, rng.random(n) < 0.9
        busy = rng.integers(0, 6, n) if with_busy else None
        args = (n_on, n_off, log_prev, log_cur, inf_prev, inf_cur, (0.21, 0.17), busy)
        s_kernel, s_ref = score0.copy(), score0.copy()
        own_kernel = edi.update_contradictions(s_kernel, own0, *args, **kw)
        with edi.numpy_reference():
            own_ref = edi.update_contradictions(s_ref, own0, *args, **kw)
        assert np.array_equal(s_kernel, s_ref) and np.array_equal(own_kernel, own_ref)
        assert own_ref.any() and not own_ref.all()
        score0, own0 = s_ref, own_ref


def test_dilation_kernel_equals_the_numpy_reference_at_the_borders():
    """The compiled dilation of the unreliable-pixel mask gives the numpy shifts' result, with marked pixels on
    every border and corner (no wrap-around) and offsets of a radius-2 disk."""
    import edi_live.edi as edi

    rng = np.random.default_rng(5)
    grow = UnreliablePixels(9, 7, grow_px=2)._grow
    mask = rng.random((7, 9)) < 0.08
    mask[0, 0] = mask[6, 8] = mask[3, 0] = mask[0, 5] = True
    got = edi.dilate(mask, grow)
    with edi.numpy_reference():
        want = edi.dilate(mask, grow)
    assert np.array_equal(got, want) and want.sum() > mask.sum()
    # an independent oracle: each pixel is marked iff some marked pixel lies within the disk around it
    ys, xs = np.nonzero(mask)
    oracle = np.zeros_like(mask)
    for y in range(7):
        for x in range(9):
            oracle[y, x] = any((y - yy, x - xx) in grow for yy, xx in zip(ys, xs))
    assert np.array_equal(got, oracle)
    assert not edi.dilate(np.zeros((7, 9), bool), grow).any()


@pytest.mark.parametrize("offsets", [[(0, 1)], [], [(1, 1), (-1, -1)]])
def test_dilation_keeps_the_mask_itself_for_any_offsets(offsets):
    """dilate is mask OR-ed with its shifts: with offsets that leave out (0, 0) the mask itself stays in."""
    import edi_live.edi as edi

    mask = np.random.default_rng(6).random((5, 6)) < 0.2
    got = edi.dilate(mask, offsets)
    with edi.numpy_reference():
        want = edi.dilate(mask, offsets)
    assert np.array_equal(got, want) and (got >= mask).all()
