"""The per-event kernels that every event goes through (latent propagation with its display, flicker cycles), against
plain Python references on random events: pixels off the sensor, masked pixels, empty input, the span stop."""

from __future__ import annotations

import math

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE
from edi_live.edi import _kernels_stream
from edi_live.edi.latent import display_buckets

pytestmark = pytest.mark.skipif(not edi.have_numba(), reason="the kernels need numba")


def _random_events(rng, n, width, height, t1, off_sensor=0.05):
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(0, t1, n))
    ev["x"] = rng.integers(0, width, n)
    ev["y"] = rng.integers(0, height, n)
    out = rng.random(n) < off_sensor
    ev["x"][out] = width + rng.integers(0, 3, int(out.sum()))
    ev["p"] = rng.random(n) < 0.5
    return ev


def _display_reference(v: float, gain: float) -> int:
    """clip(gain * exp(v), 0, 255) rounded, in float64 as the kernel's formula reads."""
    return int(min(gain * math.exp(min(v, 6.0)) + 0.5, 255.0))


def _propagate_reference(flat, disp, acc_on, acc_off, ev, width, height, mask, d_on, d_off, gain=1.0):
    """One event at a time: log L += step in float64, clipped, stored as float32; the display from the float64."""
    applied = 0
    for x, y, p in zip(ev["x"].tolist(), ev["y"].tolist(), ev["p"].tolist()):
        if x >= width or y >= height:
            continue
        q = y * width + x
        if mask is not None and mask.reshape(-1)[q]:
            continue
        v = min(max(float(flat[q]) + (d_on if p else d_off), edi.LOG_MIN), edi.LOG_MAX)
        flat[q] = np.float32(v)
        disp[q] = _display_reference(v, gain)
        if p:
            acc_on[q] += 1
        else:
            acc_off[q] += 1
        applied += 1
    return applied


@pytest.mark.parametrize("c_on,c_off", [(0.25, 0.25), (0.9, 0.3), (4.0, 4.0)])
@pytest.mark.parametrize("masked", [False, True])
def test_propagation_and_its_display_as_the_plain_loop(c_on, c_off, masked):
    """Start values across the whole log range (below the first display step, above 255, at both clips)."""
    rng = np.random.default_rng(7)
    w, h = 40, 30
    start = rng.uniform(-3.0, 7.0, h * w).astype(np.float32)
    start[:4] = [edi.LOG_MIN, edi.LOG_MAX, -29.9, 29.9]
    mask = (rng.random((h, w)) < 0.2) if masked else None
    log_k = start.reshape(h, w).copy()
    disp_k = np.zeros((h, w), np.uint8)
    counts_k = (np.zeros(w * h, np.int64), np.zeros(w * h, np.int64))
    flat_r, disp_r = start.copy(), np.zeros(w * h, np.uint8)
    counts_r = (np.zeros(w * h, np.int64), np.zeros(w * h, np.int64))
    prop = edi.Propagator(log_k, disp_k, c_on, c_off, mask, counts_k)
    ev = _random_events(rng, 6000, w, h, 100_000)
    applied_r = 0
    for part in np.array_split(ev, 11) + [ev[:0]]:  # including an empty part
        prop.apply(part["x"], part["y"], part["p"])
        applied_r += _propagate_reference(flat_r, disp_r, *counts_r, part, w, h, mask, c_on, -c_off)
    np.testing.assert_array_equal(log_k.reshape(-1), flat_r)
    np.testing.assert_array_equal(disp_k.reshape(-1), disp_r)
    np.testing.assert_array_equal(counts_k[0], counts_r[0])
    np.testing.assert_array_equal(counts_k[1], counts_r[1])
    assert applied_r > 4000 and len(set(disp_r.tolist())) > (100 if c_on < 1 else 2)
    # propagate_log (one call, no counts) gives the same
    log_1, disp_1 = start.reshape(h, w).copy(), np.zeros((h, w), np.uint8)
    assert edi.propagate_log(log_1, ev, c_on, c_off, mask=mask, display=disp_1) == applied_r
    np.testing.assert_array_equal(log_1, log_k)
    np.testing.assert_array_equal(disp_1, disp_k)


@pytest.mark.parametrize("gain", [1.0, 0.7, 3.0])
def test_the_display_table_equals_exp_at_every_step_and_between(gain):
    """Every value 1..255 starts where exp says, to the last bit: each double within 300 steps of where gain *
    exp(v) + 0.5 crosses k, and random doubles over the whole clipped range."""
    tables = display_buckets(gain)
    assert tables is not None
    k = np.arange(1, 256)
    steps = np.log((k - 0.5) / gain)
    near = (steps.view(np.int64)[:, None] + np.arange(-300, 301)[None, :]).reshape(-1).view(np.float64)
    rng = np.random.default_rng(1)
    probe = np.concatenate([near, rng.uniform(edi.LOG_MIN, edi.LOG_MAX, 20_000), rng.uniform(-1, 6, 20_000),
                            [edi.LOG_MIN, edi.LOG_MAX, 6.0]])
    got = np.empty(probe.size, np.uint8)
    _kernels_stream.display_u8_table(probe, *tables, got)
    want = np.array([_display_reference(v, gain) for v in probe.tolist()], np.uint8)
    np.testing.assert_array_equal(got, want)
    assert set(got.tolist()) == set(range(256))


@pytest.mark.parametrize("gain", [0.1, 0.5])
def test_a_gain_without_a_table_propagates_as_the_plain_loop(gain):
    """255 is never reached below log L = 6 at these gains: no table, and the kernel renders with exp; the log
    image is the same per-event clipped sum as with any gain (the gain only scales the display)."""
    assert display_buckets(gain) is None
    rng = np.random.default_rng(3)
    w, h = 30, 20
    start = rng.uniform(-3.0, 7.0, h * w).astype(np.float32)
    ev = _random_events(rng, 3000, w, h, 50_000)
    log_k, disp_k = start.reshape(h, w).copy(), np.zeros((h, w), np.uint8)
    flat_r, disp_r = start.copy(), np.zeros(w * h, np.uint8)
    counts_r = (np.zeros(w * h, np.int64), np.zeros(w * h, np.int64))
    applied = edi.propagate_log(log_k, ev, 0.6, 0.4, display=disp_k, gain=gain)
    assert applied == _propagate_reference(flat_r, disp_r, *counts_r, ev, w, h, None, 0.6, -0.4, gain)
    np.testing.assert_array_equal(log_k.reshape(-1), flat_r)
    np.testing.assert_array_equal(disp_k.reshape(-1), disp_r)


def test_a_nan_log_value_renders_black():
    """As the exp formula's conversion gave: 0, not a read outside the table."""
    got = np.full(2, 7, np.uint8)
    _kernels_stream.display_u8_table(np.array([np.nan, -np.nan]), *display_buckets(1.0), got)
    np.testing.assert_array_equal(got, [0, 0])


def test_a_propagator_keeps_the_path_it_was_built_with():
    """Built under numpy_reference() (tests, benchmarks), applied after it: still the numpy path, and the same
    log image as the compiled one."""
    rng = np.random.default_rng(4)
    ev = _random_events(rng, 500, 10, 8, 10_000)
    images = []
    for reference in (True, False):
        log_l, disp = np.zeros((8, 10), np.float32), np.zeros((8, 10), np.uint8)
        with (edi.numpy_reference() if reference else _Nothing()):
            prop = edi.Propagator(log_l, disp, 0.3, 0.2, None, None)
        prop.apply(ev["x"], ev["y"], ev["p"])
        images.append(log_l)
    np.testing.assert_allclose(images[0], images[1], atol=1e-5)


def _flicker_run(ev, w, h, *, reference, span_us, parts):
    state = edi.FlickerState(w, h)
    flagged, reads = [], []
    ctx = edi.numpy_reference() if reference else _Nothing()
    with ctx:
        for part in np.array_split(ev, parts) + [ev[:0]]:
            pos = 0
            while True:  # as FlickerPixels reads: on from each stop
                got = edi.flicker_cycles(part[pos:], state, min_period_us=7300, max_period_us=11300, cycles=2,
                                         hold_us=30_000, span_us=span_us)
                flagged.append(got.tolist())
                read = int(state.read[0])
                reads.append(read)
                pos += read
                if pos >= len(part):
                    break
    return flagged, reads, state.bits.copy(), state.times.copy(), int(state.changes[0])


class _Nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _lamp(x, y, period_us, t0, t1, jitter, rng):
    rows, t = [], float(t0)
    while t < t1:
        for k in range(int(rng.integers(1, 4))):
            rows.append((int(t) + 90 * k + int(rng.integers(0, jitter + 1)), x, y, True))
            rows.append((int(t + period_us / 2) + 90 * k, x, y, False))
        t += period_us
    return rows


@pytest.mark.parametrize("span_us", [0, 1000, 3000])
def test_flicker_cycles_as_the_plain_loop_with_its_span_stop(span_us):
    """Lamps that start and stop (flags set and released), noise on and off the sensor, random reads."""
    rng = np.random.default_rng(11)
    w, h = 6, 5
    rows = []
    for j in range(8):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        t0 = int(rng.integers(0, 150_000))
        rows += _lamp(x, y, float(rng.choice([10_000, 8_333, 17_000, 5_000])), t0, t0 + int(rng.integers(20_000,
                                                                                                          120_000)),
                      400, rng)
    noise = _random_events(rng, 4000, w, h, 300_000, off_sensor=0.1)
    rows += list(zip(noise["t"].tolist(), noise["x"].tolist(), noise["y"].tolist(), noise["p"].tolist()))
    rows.sort()
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for i, r in enumerate(rows):
        ev[i] = r
    for parts in (1, 13):
        kernel = _flicker_run(ev, w, h, reference=False, span_us=span_us, parts=parts)
        ref = _flicker_run(ev, w, h, reference=True, span_us=span_us, parts=parts)
        assert kernel[0] == ref[0] and kernel[1] == ref[1] and kernel[4] == ref[4]
        np.testing.assert_array_equal(kernel[2], ref[2])
        np.testing.assert_array_equal(kernel[3], ref[3])
        assert kernel[4] >= 4 and any(kernel[0])  # flags were set and released
        if span_us:
            assert len(kernel[1]) > parts + 1  # the span stop cut reads


@pytest.mark.parametrize("sign", [1, -1])
def test_counts_with_a_floor_equal_the_numpy_reference_and_a_plain_count(rng, sign):
    """add_counts(..., floor=True) adds (or takes off) a window's events and raises counts below 0 to 0: the kernel
    floors as it counts (counts >= 0 before), the numpy reference floors the whole image once at the end; both
    equal a count done here."""
    w, h = 13, 9
    ev = _random_events(rng, 3000, w, h, 50_000)
    start = rng.integers(0, 4, w * h).astype(np.int64)  # many pixels hold fewer than the events taken off
    mask = rng.random((h, w)) < 0.1
    results = []
    for reference in (False, True):
        on, off = start.copy(), start[::-1].copy()
        if reference:
            with edi.numpy_reference():
                edi.add_counts(ev, w, h, on, off, t0=10_000, t1=30_000, mask=mask, sign=sign, floor=True)
        else:
            edi.add_counts(ev, w, h, on, off, t0=10_000, t1=30_000, mask=mask, sign=sign, floor=True)
        results.append((on, off))
    inside = (ev["t"] >= 10_000) & (ev["t"] <= 30_000) & (ev["x"] < w) & (ev["y"] < h)
    q = ev["y"][inside].astype(np.int64) * w + ev["x"][inside]
    keep = ~mask.reshape(-1)[q]
    p = ev["p"][inside]
    for got in results:
        for polarity, counts, first in ((True, got[0], start), (False, got[1], start[::-1])):
            want = first.copy()
            np.add.at(want, q[keep & (p == polarity)], sign)
            assert np.array_equal(counts, np.maximum(want, 0))
    if sign < 0:
        assert (start - np.bincount(q[keep & p], minlength=w * h) < 0).any()  # the floor had work to do
