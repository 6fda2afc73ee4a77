"""RunningDivisor: the double integral fed in parts while an exposure runs equals log_divisor_events on all of its
events at once, bit for bit, for any split of the events, with one or two thresholds, masks, hot-pixel counts and
the counts after f; and the numpy reference agrees."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE

W, H = 23, 17


def _events(rng, n=6000, t0=1_000, t1=41_000):
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(t0, t1, n)) // 7 * 7  # many events share a time, also across the cuts
    ev["x"] = rng.integers(0, W + 2, n)  # a few off the sensor: ignored by both
    ev["y"] = rng.integers(0, H, n)
    ev["p"] = rng.random(n) < 0.6
    return ev


def _parts(ev, rng, overlap: bool):
    """Time-ordered batches at random cuts; with `overlap`, each batch repeats the tail of the previous one."""
    cuts = np.sort(rng.integers(0, ev.size, 7))
    out, lo = [], 0
    for c in [*cuts, ev.size]:
        start = max(0, lo - 50) if overlap else lo
        out.append(ev[start:c])
        lo = c
    return out


@pytest.mark.parametrize("reference", [False, True])
@pytest.mark.parametrize("c_on, c_off", [(0.2, 0.2), (0.25, 0.17)])
@pytest.mark.parametrize("overlap", [False, True])
def test_fed_in_parts_equals_all_at_once(rng, reference, c_on, c_off, overlap):
    ev = _events(rng)
    ts, te = 5_000, 37_000  # events before and after the exposure are ignored
    f = (ts + te) // 2
    mask = np.zeros(W * H, bool)
    mask[rng.integers(0, W * H, 20)] = True
    with edi.numpy_reference() if reference else _nothing():
        counts_once, counts_run = np.zeros(W * H, np.int64), np.zeros(W * H, np.int64)
        acc_once = (np.zeros(W * H, np.int64), np.zeros(W * H, np.int64))
        acc_run = (np.zeros(W * H, np.int64), np.zeros(W * H, np.int64))
        once = edi.log_divisor_events(ev, W, H, ts, te, f, c_on, c_off, mask=mask, event_counts=counts_once,
                                      counts_after_f=acc_once)
        run = edi.RunningDivisor(W, H, ts, te, f, c_on, c_off, mask=mask, event_counts=counts_run)
        for k, part in enumerate(_parts(ev, rng, overlap)):
            (run.feed_from if overlap and k else run.feed)(part)
        got = run.finish(counts_after_f=acc_run)
    order_once, order_run = np.argsort(once[0]), np.argsort(got[0])
    assert np.array_equal(once[0][order_once], got[0][order_run])
    assert np.array_equal(once[1][order_once], got[1][order_run])  # bit-identical, not merely close
    if once[2] is None:
        assert got[2] is None
    else:
        assert np.array_equal(once[2][order_once], got[2][order_run])
    assert np.array_equal(counts_once, counts_run)
    assert all(np.array_equal(a, b) for a, b in zip(acc_once, acc_run))
    assert run.events_fed == edi.window(ev, ts, te).size


def test_matches_names_exactly_the_divisor_it_computes(rng):
    mask = np.zeros(W * H, bool)
    run = edi.RunningDivisor(W, H, 0, 10_000, 5_000, 0.2, 0.2, mask=mask)
    assert run.matches(0, 10_000, 5_000, 0.2, 0.2, mask, None)
    assert not run.matches(0, 10_000, 5_000, 0.21, 0.2, mask, None)  # c changed
    assert not run.matches(0, 10_001, 5_000, 0.2, 0.2, mask, None)  # another window
    assert not run.matches(0, 10_000, 5_000, 0.2, 0.2, mask.copy(), None)  # another mask, even if equal now


@pytest.mark.parametrize("reference", [False, True])
@pytest.mark.parametrize("c_on, c_off", [(0.2, 0.2), (0.25, 0.17)])
def test_events_are_counted_only_at_the_finish(rng, reference, c_on, c_off):
    # a running integral may be fed and then dropped (its window was not the exposure's): it must not have
    # counted anything by then, masked events included, or the deblur that reads the events counts them twice
    ev = _events(rng)
    mask = np.zeros(W * H, bool)
    mask[rng.integers(0, W * H, 20)] = True
    counts = np.zeros(W * H, np.int64)
    with edi.numpy_reference() if reference else _nothing():
        run = edi.RunningDivisor(W, H, 5_000, 37_000, 21_000, c_on, c_off, mask=mask, event_counts=counts)
        run.feed(ev)
    assert run.events_fed > 0 and not counts.any()


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.parametrize("reference", [False, True])
@pytest.mark.parametrize("c_on, c_off", [(0.2, 0.2), (0.25, 0.17)])
@pytest.mark.parametrize("counting", [False, True])
def test_a_mask_changed_part_way_equals_that_mask_from_the_start(rng, reference, c_on, c_off, counting):
    """Pixels flagged or released while the exposure's events were being fed: remask() then the rest of the
    events give what log_divisor_events gives with the new mask on all of them, bit for bit."""
    ev = _events(rng)
    ts, te = 5_000, 37_000
    f = (ts + te) // 2
    armed = np.zeros(W * H, bool)
    armed[rng.integers(0, W * H, 40)] = True
    new = armed.copy()
    new[rng.integers(0, W * H, 30)] = True  # flagged since
    new[np.flatnonzero(armed)[:15]] = False  # released since
    with edi.numpy_reference() if reference else _nothing():
        counts_once = np.zeros(W * H, np.int64) if counting else None
        counts_run = np.zeros(W * H, np.int64) if counting else None
        acc_once = (np.zeros(W * H, np.int64), np.zeros(W * H, np.int64))
        acc_run = (np.zeros(W * H, np.int64), np.zeros(W * H, np.int64))
        once = edi.log_divisor_events(ev, W, H, ts, te, f, c_on, c_off, mask=new, event_counts=counts_once,
                                      counts_after_f=acc_once)
        run = edi.RunningDivisor(W, H, ts, te, f, c_on, c_off, mask=armed, event_counts=counts_run)
        cut = int(np.searchsorted(ev["t"], (ts + te) // 2 + 3_000))  # part way, past f
        run.feed(ev[:cut])
        run.remask(new, ev)  # the deblur's batch: every event from before the exposure on
        run.feed_from(ev)
        got = run.finish(counts_after_f=acc_run)
    order_once, order_run = np.argsort(once[0]), np.argsort(got[0])
    assert np.array_equal(once[0][order_once], got[0][order_run])
    assert np.array_equal(once[1][order_once], got[1][order_run])
    if once[2] is not None:
        assert np.array_equal(once[2][order_once], got[2][order_run])
    if counting:
        assert np.array_equal(counts_once, counts_run)
    assert all(np.array_equal(a, b) for a, b in zip(acc_once, acc_run))


@pytest.mark.parametrize("two", [False, True])
@pytest.mark.parametrize("counting", [False, True])
@pytest.mark.parametrize("old_none, new_none", [(False, False), (True, False), (False, True)])
def test_the_remask_pixel_pass_equals_its_numpy_expression(rng, two, counting, old_none, new_none):
    """remask's compiled pass over the pixels: an active pixel (seen 1 or 2) masked since leaves the integral (its
    OFF count joins `on` with two thresholds; seen 3 if counting, else 0), a pixel released since restarts (seen 0)
    and is marked in `back`; the rest is untouched. Checked against the rule written with numpy masks."""
    from edi_live.edi import _backend, _kernels_pixels, _kernels_stream

    npix = W * H
    old = None if old_none else rng.random(npix) < 0.3
    new = None if new_none else rng.random(npix) < 0.3
    seen = rng.integers(0, 4, npix).astype(np.uint8)
    state = np.zeros(npix, _kernels_stream.DIVISOR_STATE_TWO)
    state["on"], state["off"] = rng.integers(0, 50, npix), rng.integers(0, 50, npix)
    o = np.zeros(npix, bool) if old is None else old
    n = np.zeros(npix, bool) if new is None else new
    gone = n & ~o & ((seen == 1) | (seen == 2))
    released = o & ~n
    want_on = state["on"] + np.where(gone & two, state["off"], 0)
    want_seen = seen.copy()
    want_seen[gone] = 3 if counting else 0
    want_seen[released] = 0
    back = np.zeros(npix, bool)
    got = _kernels_pixels.remask_divisor(*_backend.mask_arg(old), *_backend.mask_arg(new), seen, state["on"],
                                         state["off"], two, counting, back)
    assert got == (int(gone.sum()), int(released.sum()))
    assert (gone.any() or new is None) and (released.any() or old is None)  # the case has something to do
    assert np.array_equal(seen, want_seen)
    assert np.array_equal(state["on"], want_on)
    assert np.array_equal(back, released)
