"""Baselines (tools/baselines.py) on hand-computable cases, and the complementary filter's closed form
against a literal per-event implementation of Scheerlinck et al.'s recursion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edi_live.datatypes import EVENT_DTYPE, Frame
from tools import baselines as bl


def _events(rows):
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for i, (t, x, y, p) in enumerate(rows):
        ev[i] = (t, x, y, p)
    return ev


def _frame(value, ts=0, te=100, w=4, h=3):
    img = np.full((h, w), value, np.uint8) if np.isscalar(value) else np.asarray(value, np.uint8)
    return Frame(image=img, exposure_start_us=ts, exposure_end_us=te)


def test_blurry_is_the_frame_as_float():
    f = _frame(np.arange(12).reshape(3, 4))
    out = bl.blurry(f)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, np.arange(12).reshape(3, 4))


def test_signed_log_increment_counts_the_half_open_window_both_ways():
    ev = _events([(10, 1, 0, True), (20, 1, 0, True), (30, 1, 0, False), (40, 3, 1, True)])
    inc = bl.signed_log_increment(ev, 4, 3, 0.2, 0.3, 0, 25)
    assert inc[0, 1] == pytest.approx(0.4) and np.count_nonzero(inc) == 1
    back = bl.signed_log_increment(ev, 4, 3, 0.2, 0.3, 25, 0)
    assert back[0, 1] == pytest.approx(-0.4)
    full = bl.signed_log_increment(ev, 4, 3, 0.2, 0.3, 0, 40)
    assert full[0, 1] == pytest.approx(0.1) and full[1, 3] == pytest.approx(0.2)
    # the event exactly at t_from is not counted, the one at t_to is
    assert bl.signed_log_increment(ev, 4, 3, 0.2, 0.3, 10, 20)[0, 1] == pytest.approx(0.2)


def test_direct_integration_multiplies_the_frame_by_exp_of_the_events_after_mid_exposure():
    f = _frame(100, ts=0, te=100)  # mid-exposure 50
    ev = _events([(40, 0, 0, True), (60, 1, 0, True), (70, 1, 0, True), (80, 2, 1, False)])
    out = bl.direct_integration(f, ev, 90, 0.2, 0.5)
    expected = np.full((3, 4), 100.0)
    expected[0, 1] = 100 * math.exp(0.4)
    expected[1, 2] = 100 * math.exp(-0.5)
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    # going back to t=30 undoes the ON event at 40 (it lies between t and the reference)
    back = bl.direct_integration(f, ev, 30, 0.2, 0.5)
    assert back[0, 0] == pytest.approx(100 * math.exp(-0.2), rel=1e-6)
    assert back[0, 1] == pytest.approx(100.0)


def test_complementary_filter_without_events_returns_the_frame():
    cf = bl.ComplementaryFilter(4, 3, 0.2, 0.2, cutoff_hz=5.0)
    cf.add_frame(_frame(80, 0, 100))
    np.testing.assert_allclose(cf.image_at(5_000), 80.0, rtol=1e-6)
    cf.add_frame(_frame(120, 1_000, 1_100))
    # the state decays from the old frame towards the new one with time constant 1/alpha
    alpha = 2 * math.pi * 5.0
    t = 1_100 + 50_000
    expected = math.exp(math.log(121) + math.exp(-alpha * 0.05) * (math.log(81) - math.log(121))) - 1
    np.testing.assert_allclose(cf.image_at(t), expected, rtol=1e-6)


def test_complementary_filter_single_event_decays_exponentially():
    cf = bl.ComplementaryFilter(4, 3, 0.3, 0.3, cutoff_hz=2.0, eps=0.0)
    cf.add_frame(_frame(100, 0, 100))
    cf.add_events(_events([(1_000, 2, 1, True)]))
    alpha = 2 * math.pi * 2.0
    out = cf.image_at(101_000)
    assert out[1, 2] == pytest.approx(100 * math.exp(0.3 * math.exp(-alpha * 0.1)), rel=1e-6)
    assert out[0, 0] == pytest.approx(100.0, rel=1e-6)
    # cutoff 0: pure direct integration
    cf0 = bl.ComplementaryFilter(4, 3, 0.3, 0.3, cutoff_hz=0.0, eps=0.0)
    cf0.add_frame(_frame(100, 0, 100))
    cf0.add_events(_events([(1_000, 2, 1, True), (2_000, 2, 1, True), (3_000, 2, 1, False)]))
    assert cf0.image_at(500_000)[1, 2] == pytest.approx(100 * math.exp(0.3), rel=1e-6)


def _reference_cf(frames, events, query_t, w, h, c_on, c_off, alpha, eps):
    """Literal per-event recursion: per-pixel state and timestamps, global decay at frames and output."""
    log_l = None
    log_f = None
    t_pix = None
    timeline = sorted([(f.exposure_end_us, 0, f) for f in frames] + [(int(e["t"]), 1, e) for e in events],
                      key=lambda x: (x[0], x[1]))
    for t, kind, item in timeline:
        if kind == 0:
            new = np.log(item.image.astype(float) + eps)
            if log_l is None:
                log_l, t_pix = new.copy(), np.full((h, w), float(t))
            else:
                beta = np.exp(-alpha * (t - t_pix) * 1e-6)
                log_l = beta * log_l + (1 - beta) * log_f
                t_pix[:] = t
            log_f = new
        elif log_l is not None:
            x, y = int(item["x"]), int(item["y"])
            beta = math.exp(-alpha * (t - t_pix[y, x]) * 1e-6)
            log_l[y, x] = beta * log_l[y, x] + (1 - beta) * log_f[y, x] + (c_on if item["p"] else -c_off)
            t_pix[y, x] = t
    beta = np.exp(-alpha * (query_t - t_pix) * 1e-6)
    return np.exp(beta * log_l + (1 - beta) * log_f) - eps


def test_complementary_filter_closed_form_equals_the_per_event_recursion(rng):
    w, h, c_on, c_off, cutoff = 5, 4, 0.25, 0.35, 3.0
    frames = [Frame(image=rng.integers(1, 255, (h, w)).astype(np.uint8), exposure_start_us=k * 20_000,
                    exposure_end_us=k * 20_000 + 10_000) for k in range(4)]
    n = 300
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, 80_000, n))
    ev["x"], ev["y"], ev["p"] = rng.integers(0, w, n), rng.integers(0, h, n), rng.random(n) < 0.5
    query = 75_000
    cf = bl.ComplementaryFilter(w, h, c_on, c_off, cutoff_hz=cutoff)
    pos = 0
    for f in frames:  # feed in time order, each frame after its events (events at the same µs first)
        stop = int(np.searchsorted(ev["t"], f.exposure_end_us, side="right"))
        cf.add_events(ev[pos:stop])
        pos = stop
        cf.add_frame(f)
    cf.add_events(ev[pos:int(np.searchsorted(ev["t"], query, side="right"))])
    expected = _reference_cf(frames, ev[ev["t"] <= query], query, w, h, c_on, c_off, 2 * math.pi * cutoff, 1.0)
    np.testing.assert_allclose(cf.image_at(query), expected, rtol=1e-5)
