"""EDI math: the exact double integral against brute force, deblurring, latent propagation, and stability."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE


def random_events(rng, n, width, height, t0, t1):
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = np.sort(rng.integers(t0, t1 + 1, n))
    ev["x"] = rng.integers(0, width, n)
    ev["y"] = rng.integers(0, height, n)
    ev["p"] = rng.random(n) < 0.5
    return ev


def brute_divisor(events, width, height, ts, te, f, c_on, c_off):
    """(1/T) * sum over every 1-µs step of exp(c E) sampled at the step's midpoint: exact for integer event times."""
    s = np.arange(ts, te) + 0.5
    out = np.ones(width * height)
    idx = events["y"].astype(np.int64) * width + events["x"]
    for q in np.unique(idx):
        ev = events[idx == q]
        t_on = np.sort(ev["t"][ev["p"]])
        t_off = np.sort(ev["t"][~ev["p"]])
        n_on = np.searchsorted(t_on, s, side="right") - np.searchsorted(t_on, f, side="right")
        n_off = np.searchsorted(t_off, s, side="right") - np.searchsorted(t_off, f, side="right")
        out[q] = np.mean(np.exp(c_on * n_on - c_off * n_off))
    return out


@pytest.fixture(params=["numba", "numpy"])
def backend(request):
    if request.param == "numpy":
        with edi.numpy_reference():
            yield request.param
    else:
        yield request.param


@pytest.mark.parametrize("seed", range(6))
def test_divisor_matches_brute_force_integral(backend, seed):
    rng = np.random.default_rng(seed)
    w, h = 5, 4
    ts, te = 1000, 1000 + int(rng.integers(50, 3000))
    f = int(rng.integers(ts, te + 1))
    ev = random_events(rng, int(rng.integers(1, 120)), w, h, ts - 500, te + 500)  # some outside the exposure
    table = edi.build_level_table(ev, w, h, ts, te, f)
    for c_on, c_off in [(0.2, 0.2), (0.35, 0.15), (1.7, 1.7), (0.01, 0.4)]:
        want = brute_divisor(ev[(ev["t"] >= ts) & (ev["t"] <= te)], w, h, ts, te, f, c_on, c_off)
        got = np.ones(w * h)
        got[table.pixels] = np.exp(edi.log_divisor(table, c_on, c_off))
        np.testing.assert_allclose(got, want, rtol=1e-6)
        # the one-pass path for a known c gives the same numbers
        pix, ld, delta_end = edi.log_divisor_events(ev, w, h, ts, te, f, c_on, c_off)
        fast = np.ones(w * h)
        fast[pix] = np.exp(ld)
        np.testing.assert_allclose(fast, want, rtol=1e-6)
        if delta_end is not None:  # c * E(f -> te), when the fast path provides it
            dense = edi.event_delta(ev, w, h, c_on, c_off, t0=f + 1, t1=te).reshape(-1)
            np.testing.assert_allclose(delta_end, dense[pix], atol=1e-5)


def test_numba_and_numpy_tables_agree(rng):
    ev = random_events(rng, 5000, 30, 20, 0, 10_000)
    mask = rng.random((20, 30)) < 0.1
    a = edi.build_level_table(ev, 30, 20, 0, 10_000, 4321, mask=mask)
    with edi.numpy_reference():
        b = edi.build_level_table(ev, 30, 20, 0, 10_000, 4321, mask=mask)
    for name in a.__slots__:
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-12, err_msg=name)


def test_masked_and_out_of_range_events_are_skipped_but_counted(backend):
    ev = np.zeros(4, EVENT_DTYPE)
    ev["t"] = [10, 20, 30, 40]
    ev["x"] = [0, 1, 7, 1]  # x = 7 is outside a 4-wide sensor
    ev["y"] = [0, 0, 0, 0]
    ev["p"] = True
    mask = np.zeros((2, 4), bool)
    mask[0, 1] = True
    counts = np.zeros(8, np.int64)
    table = edi.build_level_table(ev, 4, 2, 0, 100, mask=mask, event_counts=counts)
    np.testing.assert_array_equal(table.pixels, [0])
    assert table.n_events == 1
    np.testing.assert_array_equal(counts, [1, 2, 0, 0, 0, 0, 0, 0])  # masked pixel still counted (hot stats)
    n_on, n_off = edi.signed_counts(ev, 4, 2, mask=mask)
    np.testing.assert_array_equal(n_on, [1, 0, 0, 0, 0, 0, 0, 0])
    log_l = np.zeros((2, 4), np.float32)
    assert edi.propagate_log(log_l, ev, 0.5, mask=mask) == 1
    assert log_l[0, 0] == pytest.approx(0.5) and log_l[0, 1] == 0


def test_normalised_by_exposure_not_event_span(backend):
    # one ON event at the very end: the pixel spent the whole exposure at level -1 relative to f = te
    ev = np.zeros(1, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = 1900, 0, 0, True
    table = edi.build_level_table(ev, 1, 1, 1000, 2000, 2000)
    c = 0.5
    want = (900 * np.exp(-c) + 100 * 1.0) / 1000
    assert np.exp(edi.log_divisor(table, c))[0] == pytest.approx(want, rel=1e-12)


def test_deblur_inverts_the_blur_model(backend, rng):
    w, h, ts, te = 8, 6, 0, 4000
    ev = random_events(rng, 300, w, h, ts, te)
    sharp = rng.uniform(20, 200, (h, w)).astype(np.float32)
    c = 0.15
    blurry = sharp * brute_divisor(ev, w, h, ts, te, 2000, c, c).reshape(h, w)
    table = edi.build_level_table(ev, w, h, ts, te)
    informative = np.ones((h, w), bool)
    np.testing.assert_allclose(edi.deblur(blurry, table, c, informative=informative), sharp, rtol=1e-5)


def test_pixels_without_events_or_saturated_keep_b(backend):
    w, h = 4, 1
    ev = np.zeros(6, EVENT_DTYPE)
    ev["t"] = [100, 200, 300, 100, 200, 300]
    ev["x"] = [1, 1, 1, 2, 2, 2]
    ev["p"] = True
    image = np.array([[50, 50, 255, 0]], np.uint8)
    b, informative = edi.blurry_to_float(image)
    table = edi.build_level_table(ev, w, h, 0, 1000)
    out = edi.deblur(b, table, 0.3, informative=informative)
    assert out[0, 0] == pytest.approx(50, rel=1e-5)  # no events
    assert out[0, 1] > 50  # it brightened before f = 500, so L(f) is above the exposure mean
    assert out[0, 2] == pytest.approx(255, rel=1e-5)  # saturated: uninformative, kept
    assert out[0, 3] == pytest.approx(0, abs=1)


def test_latent_propagation_forward_back_and_against_formula(backend, rng):
    w, h = 7, 5
    log_l = rng.uniform(1, 5, (h, w)).astype(np.float32)
    start = log_l.copy()
    ev = random_events(rng, 400, w, h, 0, 1000)
    display = np.zeros((h, w), np.uint8)
    edi.propagate_log(log_l, ev, 0.3, 0.2, display=display)
    n_on, n_off = edi.signed_counts(ev, w, h)
    want = start + (0.3 * n_on - 0.2 * n_off).reshape(h, w)
    np.testing.assert_allclose(log_l, np.clip(want, edi.LOG_MIN, edi.LOG_MAX), atol=1e-4)
    touched = (n_on + n_off).reshape(h, w) > 0
    np.testing.assert_array_equal(display[touched], edi.to_uint8(log_l[touched]))
    assert (display[~touched] == 0).all()  # untouched pixels were not rewritten
    edi.propagate_log(log_l, ev, 0.3, 0.2, sign=-1)
    np.testing.assert_allclose(log_l, start, atol=1e-4)


@pytest.mark.parametrize("polarity", [True, False])
@pytest.mark.parametrize("c,c_off", [(0.01, None), (0.3, None), (2.0, None), (0.3, 0.1), (0.1, 2.0)])
def test_ten_thousand_events_at_one_pixel(backend, polarity, c, c_off):
    # with two thresholds the single-pass kernel's weight leaves [1e-150, 1e150] within a few hundred events:
    # its slow path (exponent from the counts, rebase) must give the same exact value
    ev = np.zeros(10_000, EVENT_DTYPE)
    ev["t"] = np.linspace(0, 20_000, 10_000).astype(np.int64)
    ev["p"] = polarity
    step = c if polarity or c_off is None else c_off
    table = edi.build_level_table(ev, 1, 1, 0, 20_000)
    ld = edi.log_divisor(table, c, c_off)
    pix, ld_fast, _ = edi.log_divisor_events(ev, 1, 1, 0, 20_000, None, c, c_off)
    # analytic: levels k - 5000 for ~2 µs each -> log D = log mean_k exp(c (k - n_f)); n_f = events <= f
    n_f = int(np.count_nonzero(ev["t"] <= 10_000))
    seg = np.diff(np.r_[0, ev["t"], 20_000]).astype(float)
    levels = np.arange(10_001) - n_f if polarity else n_f - np.arange(10_001)
    a = step * levels
    want = a.max() + np.log(np.sum(seg * np.exp(a - a.max())) / 20_000)
    assert np.isfinite(ld).all() and ld[0] == pytest.approx(want, rel=1e-9)
    assert ld_fast[0] == pytest.approx(want, rel=1e-9)
    b, informative = edi.blurry_to_float(np.array([[128]], np.uint8))
    out = edi.deblur(b, table, c, c_off, informative=informative)
    assert np.isfinite(out).all() and (out >= 0).all()


@pytest.mark.parametrize("polarity", [True, False])
@pytest.mark.parametrize("c_off", [2.0, 0.5])
def test_bursts_with_zero_dwell_at_the_exposure_edges(polarity, c_off):
    # 5000 events at ts and 5000 at te: the pixel sits at one level for the whole exposure (D = 1 at f)
    ev = np.zeros(10_000, EVENT_DTYPE)
    ev["t"][5000:] = 7
    ev["p"] = polarity
    table = edi.build_level_table(ev, 1, 1, 0, 7, 3)
    _, ld_fast, delta = edi.log_divisor_events(ev, 1, 1, 0, 7, 3, 2.0, c_off)
    assert edi.log_divisor(table, 2.0, c_off)[0] == pytest.approx(0.0, abs=1e-12)
    assert ld_fast[0] == pytest.approx(0.0, abs=1e-12)
    if delta is not None:
        assert delta[0] == pytest.approx(5000 * (2.0 if polarity else -c_off))


@pytest.mark.parametrize("black, gamma", [(10.0, 1.0), (np.float64(4.0), 1.0), (3.7, 0.9), (0.0, 2.2)])
@pytest.mark.parametrize("saturation", [None, 250.0])
def test_a_non_linear_uint8_frame_looks_up_what_the_numpy_formulas_give(black, gamma, saturation, rng):
    """B and the informative mask of a uint8 frame with a black level or a gamma come from a 256-entry table: bit
    for bit the numpy formulas' result, for every value, anywhere in a full-size frame (also read-only or
    strided)."""
    image = rng.integers(0, 256, (180, 240)).astype(np.uint8)
    image[0, :256 - 240], image[-1] = np.arange(16), np.arange(16, 256)  # every value, at the start and the end
    frozen = image.copy()
    frozen.setflags(write=False)
    for frame in (image, frozen, image[:, ::3]):
        b, informative = edi.blurry_to_float(frame, saturation=saturation, black_level=black, gamma=gamma)
        with edi.numpy_reference():
            b_ref, informative_ref = edi.blurry_to_float(frame, saturation=saturation, black_level=black,
                                                         gamma=gamma)
        assert b.dtype == np.float32 and b.shape == frame.shape and informative.shape == frame.shape
        assert np.array_equal(b.view(np.uint32), b_ref.view(np.uint32))
        assert np.array_equal(informative, informative_ref) and not informative.all() and informative.any()


@pytest.mark.parametrize("black", [0.0, 10.0, 37.5])
def test_black_level_is_taken_off_b_in_every_path(black, rng):
    image = rng.integers(0, 256, (6, 9)).astype(np.uint8)
    b, informative = edi.blurry_to_float(image, black_level=black)
    np.testing.assert_array_equal(b, np.maximum(image.astype(np.float32) - np.float32(black), 0))
    np.testing.assert_array_equal(informative, (image > black) & (image < 255))
    # the fused finish (kernel) against its numpy reference, with events at a few pixels
    pixels = np.array([0, 5, 17, 40, 53], np.int64)
    divisor = (pixels, rng.uniform(-2, 2, pixels.size), rng.uniform(-1, 1, pixels.size).astype(np.float32))
    results = []
    for reference in (False, True):
        out = [np.empty((6, 9), np.float32), np.empty((6, 9), np.uint8), np.empty((6, 9), np.float32),
               np.empty((6, 9), np.uint8)]
        if reference:
            with edi.numpy_reference():
                edi.finish_frame_u8(image, 255.0, divisor, *out, black_level=black)
        else:
            edi.finish_frame_u8(image, 255.0, divisor, *out, black_level=black)
        results.append(out)
    for kernel, numpy_ref in zip(*results):
        tolerance = 1e-5 if kernel.dtype == np.float32 else 1
        np.testing.assert_allclose(kernel.astype(float), numpy_ref.astype(float), atol=tolerance)
    # pixels without events: log L(f) = log(max(B - black, floor)) exactly
    quiet = np.setdiff1d(np.arange(54), pixels)
    want = np.clip(np.log(np.maximum(b.reshape(-1)[quiet], edi.DARK_FLOOR)), edi.LOG_MIN, edi.LOG_MAX)
    np.testing.assert_allclose(results[0][0].reshape(-1)[quiet], want, rtol=1e-6)


def test_take_restricts_rows(backend, rng):
    ev = random_events(rng, 2000, 20, 10, 0, 5000)
    table = edi.build_level_table(ev, 20, 10, 0, 5000)
    rows = np.arange(0, table.n_active, 3)
    sub = table.take(rows)
    for k, r in enumerate(rows):  # row by row against the table's own slices
        for start, arrays in (("seg_start", ("seg_on", "seg_off", "seg_frac")), ("lvl_start", ("lvl_frac",))):
            a, b = getattr(table, start)[r], getattr(table, start)[r + 1]
            sa, sb = getattr(sub, start)[k], getattr(sub, start)[k + 1]
            for name in arrays:
                np.testing.assert_array_equal(getattr(sub, name)[sa:sb], getattr(table, name)[a:b])
    np.testing.assert_array_equal(sub.lvl_min, table.lvl_min[rows])
    np.testing.assert_array_equal(sub.pixels, table.pixels[rows])
    np.testing.assert_allclose(edi.log_divisor(sub, 0.4), edi.log_divisor(table, 0.4)[rows])
    np.testing.assert_allclose(edi.log_divisor(sub, 0.4, 0.1), edi.log_divisor(table, 0.4, 0.1)[rows])


def test_subset_events_are_the_events_at_those_pixels(backend, rng):
    ev = random_events(rng, 3000, 20, 10, 0, 5000)
    ev["x"][::50] = 25  # out of range: never selected
    only = rng.random((10, 20)) < 0.3
    got = edi.events_at_pixels(ev, 20, 10, only, 1000, 4000)
    inside = (ev["x"] < 20) & (ev["t"] >= 1000) & (ev["t"] <= 4000)
    want = ev[inside & only.reshape(-1)[np.minimum(ev["y"].astype(int) * 20 + ev["x"], 199)]]
    np.testing.assert_array_equal(got, want)


def test_hot_pixel_found_among_moving_edges(rng):
    w, h = 60, 40
    counts = np.zeros(w * h, np.int64)
    edge_pixels = rng.choice(w * h, 800, replace=False)
    counts[edge_pixels] = rng.integers(1, 25, 800)  # a moving texture: many pixels, a few events each
    counts[123] = 2000  # 1 kHz over 2 s
    mask = edi.hot_pixel_mask(counts, 2_000_000)
    assert mask[123]
    assert mask.sum() == 1


def test_background_activity_filter(backend):
    ev = np.zeros(5, EVENT_DTYPE)
    ev["t"] = [0, 100, 5000, 5100, 90_000]
    ev["x"] = [10, 11, 30, 10, 10]
    ev["y"] = [10, 10, 5, 11, 10]
    # one-sided, as a stream: each event needs a neighbour event within 1 ms BEFORE it
    state = edi.new_activity_map(40, 20)
    keep = np.r_[edi.background_activity_keep(ev[:2], 40, 20, state, 1000),
                 edi.background_activity_keep(ev[2:], 40, 20, state, 1000)]
    np.testing.assert_array_equal(keep, [False, True, False, False, False])
    # two-sided over a whole batch: the first event is supported by the one right after it
    np.testing.assert_array_equal(edi.supported_events_keep(ev, 40, 20, 1000), [True, True, False, False, False])


def test_isolated_events_found():
    ev = np.zeros(4, EVENT_DTYPE)
    ev["x"] = [5, 10, 11, 20]
    ev["y"] = [5, 10, 10, 2]
    m = edi.isolated_event_mask(ev, 30, 20)
    assert m[5, 5] and m[2, 20]
    assert not m[10, 10] and not m[10, 11]


def test_rejects_reversed_exposure():
    with pytest.raises(ValueError, match="exposure ends before it starts"):
        edi.build_level_table(np.zeros(0, EVENT_DTYPE), 2, 2, 100, 50)


# ---- numerical stability (property-based) ----

@st.composite
def hard_cases(draw):
    w = draw(st.integers(1, 6))
    h = draw(st.integers(1, 4))
    exposure = draw(st.sampled_from([1, 2, 17, 1000, 20_000, 1_000_000]))
    ts = draw(st.integers(0, 10**12))
    te = ts + exposure
    n_hot = draw(st.sampled_from([0, 1, 50, 10_000]))  # events at one pixel
    n_rand = draw(st.integers(0, 60))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    hot = np.zeros(n_hot, EVENT_DTYPE)
    hot["t"] = rng.integers(ts, te + 1, n_hot)
    polarity = draw(st.sampled_from(["on", "off", "mixed"]))
    hot["p"] = True if polarity == "on" else (False if polarity == "off" else rng.random(n_hot) < 0.5)
    rand = random_events(rng, n_rand, w, h, ts - exposure, te + exposure)  # some outside the exposure
    ev = np.concatenate([hot, rand]).astype(EVENT_DTYPE)
    ev = ev[np.argsort(ev["t"], kind="stable")]
    c_on = draw(st.floats(0.01, 2.0))
    c_off = draw(st.one_of(st.just(c_on), st.floats(0.01, 2.0)))
    b_kind = draw(st.sampled_from(["zero", "full", "random", "mixed"]))
    if b_kind == "zero":
        image = np.zeros((h, w), np.uint8)
    elif b_kind == "full":
        image = np.full((h, w), 255, np.uint8)
    else:
        image = rng.integers(0 if b_kind == "mixed" else 1, 256, (h, w)).astype(np.uint8)
    return ev, w, h, ts, te, c_on, c_off, image


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(hard_cases())
def test_deblur_and_latent_are_finite_and_non_negative(case):
    ev, w, h, ts, te, c_on, c_off, image = case
    b, informative = edi.blurry_to_float(image)
    table = edi.build_level_table(ev, w, h, ts, te)
    ld = edi.log_divisor(table, c_on, c_off)
    assert np.isfinite(ld).all()
    pix, ld_fast, delta = edi.log_divisor_events(ev, w, h, ts, te, None, c_on, c_off)
    order = np.argsort(pix)
    np.testing.assert_array_equal(pix[order], table.pixels)
    np.testing.assert_allclose(ld_fast[order], ld, rtol=1e-9, atol=1e-9)
    out = edi.deblur(b, table, c_on, c_off, informative=informative)
    assert out.shape == (h, w) and np.isfinite(out).all() and (out >= 0).all()
    # saturated / black pixels carry no information and are left as B
    np.testing.assert_allclose(out[~informative], np.clip(b[~informative], 0, None), atol=1.0)
    log_l = edi.deblur_log(b, table, c_on, c_off, informative=informative)
    display = np.zeros((h, w), np.uint8)
    edi.propagate_log(log_l, ev, c_on, c_off, display=display)
    assert np.isfinite(log_l).all()
    edi.propagate_log(log_l, ev, c_on, c_off, sign=-1)
    assert np.isfinite(log_l).all()


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 10**6), st.floats(0.01, 2.0), st.integers(0, 255))
def test_empty_exposure_keeps_b(exposure, c, value):
    image = np.full((3, 3), value, np.uint8)
    b, informative = edi.blurry_to_float(image)
    table = edi.build_level_table(np.zeros(0, EVENT_DTYPE), 3, 3, 5, 5 + exposure)
    out = edi.deblur(b, table, c, informative=informative)
    np.testing.assert_allclose(out, max(value, edi.DARK_FLOOR), rtol=1e-5)


@pytest.mark.parametrize("seed", range(4))
def test_pair_candidates_match_the_rules_pixel_by_pixel(backend, seed):
    rng = np.random.default_rng(seed)
    n = 300
    inf_p, inf_c = rng.random(n) < 0.8, rng.random(n) < 0.8
    bp, bc = rng.uniform(0, 255, n).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32)
    mask = (rng.random(n) < 0.1) if seed % 2 else None
    n_on = rng.integers(0, 2, n) * (rng.random(n) < 0.3)
    n_off = rng.integers(0, 2, n) * (rng.random(n) < 0.3)
    pix_p = np.sort(rng.choice(n, 20, replace=False)).astype(np.int64)
    pix_c = np.sort(rng.choice(n, 20, replace=False)).astype(np.int64)
    got = edi.pair_candidates(inf_p, inf_c, bp, bc, 6.0, 250.0, mask, n_on, n_off, pix_p, pix_c)
    want = [q for q in range(n) if inf_p[q] and inf_c[q] and 6 <= bp[q] <= 250 and 6 <= bc[q] <= 250
            and (mask is None or not mask[q]) and (n_on[q] + n_off[q] > 0 or q in set(pix_p) or q in set(pix_c))]
    np.testing.assert_array_equal(got, want)
