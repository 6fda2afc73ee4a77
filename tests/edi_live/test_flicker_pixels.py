"""Flickering pixels (edi_live.flicker_pixels): found from the events alone at mains periods, held while the
flicker lasts, released after; the kernel does what its numpy reference does."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE
import edi_live.flicker_pixels as fpm
from edi_live.flicker_pixels import FlickerPixels

W, H = 8, 4


def _events(rows: list[tuple[int, int, int, bool]]) -> np.ndarray:
    rows = sorted(rows)
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for i, (t, x, y, p) in enumerate(rows):
        ev[i] = (t, x, y, p)
    return ev


def _flicker(x: int, y: int, period_us: float, t0: int, t1: int, burst: int = 3) -> list:
    """A lamp pixel: each cycle an ON burst then an OFF burst of `burst` events."""
    rows, t = [], float(t0)
    while t < t1:
        for k in range(burst):
            rows.append((int(t) + 100 * k, x, y, True))
            rows.append((int(t + period_us / 2) + 100 * k, x, y, False))
        t += period_us
    return rows


def _flag_time(events: np.ndarray, x: int, y: int, **kwargs) -> int | None:
    fp = FlickerPixels(W, H, **kwargs)
    for e in events:
        fp.observe(e[None])
        if fp.mask[y, x]:
            return int(e["t"])
    return None


@pytest.mark.parametrize("hz", [100.0, 120.0, 50.0, 60.0])
def test_mains_flicker_is_flagged_after_two_cycles(hz):
    period = 1e6 / hz
    ev = _events(_flicker(2, 1, period, 0, 100_000))
    t = _flag_time(ev, 2, 1)
    # the third OFF -> ON switch (the first ON has no OFF before it): the end of two whole cycles
    assert t is not None and abs(t - 3 * period) < 200, (t, 3 * period)


@pytest.mark.parametrize("hz", [30.0, 200.0, 80.0])
def test_other_rates_are_not_flagged(hz):
    ev = _events(_flicker(2, 1, 1e6 / hz, 0, 200_000))
    assert _flag_time(ev, 2, 1) is None


def test_a_moving_edge_and_noise_are_not_flagged():
    rng = np.random.default_rng(0)
    rows = [(1000 * x + 10 * k, x, 1, True) for x in range(W) for k in range(6)]  # an edge sweeping the row
    rows += [(int(t), int(rng.integers(0, W)), 3, bool(rng.random() < 0.5))  # noise, 0.5 kHz on one row
             for t in np.sort(rng.uniform(0, 200_000, 100))]
    fp = FlickerPixels(W, H)
    fp.observe(_events(rows))
    assert fp.count == 0 and not fp.mask.any()


def test_a_pixel_is_released_once_its_flicker_stops():
    ev = _events(_flicker(2, 1, 10_000, 0, 60_000) + [(150_000, 2, 1, True)])
    fp = FlickerPixels(W, H, hold_us=30_000, idle_scan=False)  # every event read (a lamp in view; below)
    changed, flagged = fp.observe(ev[ev["t"] < 60_000])
    assert changed and flagged.tolist() == [1 * W + 2] and fp.mask[1, 2]
    changed, flagged = fp.observe(ev[ev["t"] >= 60_000])  # the next event comes long after the last cycle
    assert changed and flagged.size == 0 and not fp.mask.any() and fp.count == 0
    fp.observe(_events(_flicker(2, 1, 10_000, 200_000, 240_000)))
    assert fp.mask[1, 2], "flagged again when it flickers again"
    fp.reset()
    assert fp.count == 0 and not fp.mask.any()


def test_the_kernel_does_what_the_numpy_reference_does():
    rng = np.random.default_rng(3)
    rows = _flicker(1, 1, 10_000, 0, 120_000) + _flicker(5, 2, 8_333, 3_000, 120_000, burst=1)
    rows += _flicker(6, 3, 17_000, 0, 120_000)  # a missed switch: two periods per cycle still count
    rows += [(int(t), int(rng.integers(0, W + 2)), int(rng.integers(0, H)), bool(rng.random() < 0.5))
             for t in rng.uniform(0, 120_000, 3000)]  # noise, some of it off the sensor
    ev = _events(rows)
    results = []
    for reference in (False, True):
        state = edi.FlickerState(W, H)
        got = []
        with edi.numpy_reference() if reference else _nothing():
            for chunk in np.array_split(ev, 7):
                got.append(edi.flicker_cycles(chunk, state, min_period_us=7300, max_period_us=11300, cycles=2,
                                              hold_us=30_000).tolist())
        results.append((got, state.bits.copy(), state.run.copy(), int(state.changes[0])))
    (got_k, flag_k, run_k, ch_k), (got_r, flag_r, run_r, ch_r) = results
    assert got_k == got_r and np.array_equal(flag_k, flag_r) and np.array_equal(run_k, run_r) and ch_k == ch_r
    assert ch_k > 0 and any(got_k)


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.parametrize("gap", [False, True])
def test_a_gap_forgets_cycles_not_yet_flagged(gap):
    """Lost data breaks the cycle timing: after a gap a pixel needs two whole cycles again, also when no pixel was
    flagged before it (one regular cycle before the gap and one after must not flag it)."""
    from edi_live.reconstructor import EdiReconstructor

    from edi_live.datatypes import Frame

    rec = EdiReconstructor(W, H, c=0.2)
    rec.on_frame(Frame(np.full((H, W), 100, np.uint8), -2000, -1000), _events([]))  # a reference: events count
    events = _events(_flicker(2, 1, 10_000, 0, 46_000))
    cut = int(np.searchsorted(events["t"], 25_000))  # OFF -> ON switches at 10 and 20 ms before it: one cycle
    rec.on_events(events[:cut])
    if gap:
        rec.mark_gap()
    rec.on_events(events[cut:])  # the switch at 30 ms, then 40 ms
    assert rec.stats()["flicker_pixels"] == (0 if gap else 1)


LAMP = [(x, y) for y in range(H) for x in range(W) if (x, y) != (0, 0)][:fpm.LAMP_PIXELS + 4]


def _lamp(t0: int, t1: int) -> list:
    return [row for x, y in LAMP for row in _flicker(x, y, 10_000, t0, t1)]


def _noise(t1: int, seed: int = 1) -> list:
    rng = np.random.default_rng(seed)
    return [(int(t), int(rng.integers(0, W)), int(rng.integers(0, H)), bool(rng.random() < 0.5))
            for t in rng.uniform(0, t1, t1 // 2000)]


def test_with_nothing_flagged_only_a_scan_per_period_is_read():
    """Skipping what the scene does not need: with no lamp in view, a pixel that flickers only between two scans
    is never read (it would have been flagged had every event been read)."""
    start = fpm.SCAN_US + 20_000
    ev = _events([(0, 0, 0, True)] + _flicker(2, 1, 10_000, start, fpm.IDLE_PERIOD_US - 20_000))
    assert _flag_time(ev, 2, 1, idle_scan=False) is not None
    assert _flag_time(ev, 2, 1) is None


def test_a_lamp_that_comes_into_view_later_is_flagged_by_the_next_scan():
    on_at = fpm.IDLE_PERIOD_US + fpm.SCAN_US + 10_000  # just after a scan: the worst case
    ev = _events([(0, 0, 0, True)] + _noise(3 * fpm.IDLE_PERIOD_US) + _lamp(on_at, 3 * fpm.IDLE_PERIOD_US))
    x, y = LAMP[0]
    t = _flag_time(ev, x, y)
    assert t is not None and t <= 2 * fpm.IDLE_PERIOD_US + 3 * 10_000 + 1000, t
    assert _flag_time(ev, x, y, idle_scan=False) < t


def test_with_a_lamp_in_view_every_event_is_read():
    """Once a lamp flags LAMP_PIXELS pixels, the detector reads as it does without idle scans, and a pixel whose
    flicker stops is released at its next event."""
    ev = _events(_lamp(0, 3 * fpm.IDLE_PERIOD_US) + _noise(3 * fpm.IDLE_PERIOD_US)
                 + _flicker(0, 0, 10_000, 0, fpm.IDLE_PERIOD_US + fpm.SCAN_US + 30_000)
                 + [(2 * fpm.IDLE_PERIOD_US - 50_000, 0, 0, True)])
    got = []
    for idle in (True, False):
        fp = FlickerPixels(W, H, idle_scan=idle)
        got.append([(int(ev["t"][a + k]), None if m is None else m.tobytes(), f.tolist())
                    for a in range(0, ev.size, 97) for k, m, f in fp.steps(ev[a:a + 97])])
    assert got[0] == got[1]
    assert any(m is not None and not np.frombuffer(m, bool)[0] for t, m, f in got[0] if t > fpm.IDLE_PERIOD_US)


@pytest.mark.parametrize("chunk", [1, 13, 1000])
def test_what_is_read_does_not_depend_on_how_the_events_are_cut(chunk):
    ev = _events(_noise(3 * fpm.IDLE_PERIOD_US) + _lamp(fpm.IDLE_PERIOD_US + 100_000, 3 * fpm.IDLE_PERIOD_US)
                 + _flicker(2, 1, 10_000, 40_000, 150_000))
    results = []
    for size in (ev.size, chunk):
        fp = FlickerPixels(W, H)
        points = []
        for a in range(0, ev.size, size):
            points += [(int(ev["t"][a + k]), f.tolist(), None if m is None else m.tobytes())
                       for k, m, f in fp.steps(ev[a:a + size])]
        results.append(points)
    assert results[0] == results[1] and len(results[0]) >= 3


@pytest.mark.parametrize("chunk", [1, 1000])
def test_a_flag_found_at_the_end_of_a_scan_takes_effect_past_its_span_not_at_the_next_scan(chunk):
    """A flag change found in a scan's last STEP_US span is due at the first event past that span, which the
    detector does not read (the scan ended): it must be taken there, as when every event is read, not carried over
    the skipped range to the next scan's first event."""
    flag_at = fpm.SCAN_US - 500  # the third OFF -> ON switch: the end of two whole cycles
    lamp = [row for row in _flicker(2, 1, 10_000, flag_at - 30_000, flag_at + 1) if row[0] < fpm.SCAN_US]
    past = fpm.SCAN_US + 200  # the first event past the span, at another pixel
    ev = _events([(0, 0, 0, True)] + lamp + [(past, 5, 3, True), (fpm.SCAN_US + 300_000, 5, 3, False),
                                            (fpm.IDLE_PERIOD_US + 1_000, 6, 3, True)])
    got = []
    for idle in (True, False):
        fp = FlickerPixels(W, H, idle_scan=idle)
        got.append([(int(ev["t"][a + k]), None if m is None else np.flatnonzero(m).tolist(), f.tolist())
                    for a in range(0, ev.size, chunk) for k, m, f in fp.steps(ev[a:a + chunk])])
    assert got[1] == [(past, [1 * W + 2], [1 * W + 2])]
    assert got[0] == got[1]


@pytest.mark.parametrize("period_us", [10_000, 8_333, 20_000, 22_000])
def test_a_small_lamp_that_keeps_flickering_stays_flagged_across_the_skipped_ranges(period_us):
    """Fewer than LAMP_PIXELS pixels flagged: the detector skips most of each period, but pixels flagged by a scan
    stay flagged until a later read shows their flicker stopped. A lamp still flickering at the next scan must not
    be released at its first event there (the gap since its last cycle is the detector's, not the lamp's) and
    flagged again two cycles later: its events would go into the latent image in between."""
    small = [(1, 1), (2, 1), (3, 1)]
    ev = _events([row for x, y in small for row in _flicker(x, y, period_us, 0, 3 * fpm.IDLE_PERIOD_US + 50_000)])
    for chunk in (ev.size, 7):
        fp = FlickerPixels(W, H)
        got = [(int(ev["t"][a + k]), None if m is None else np.flatnonzero(m).tolist())
               for a in range(0, ev.size, chunk) for k, m, f in fp.steps(ev[a:a + chunk])]
        assert got == [(got[0][0], [y * W + x for x, y in small])], got


def test_a_small_lamp_that_stopped_is_released_by_the_next_scan():
    """...and a flagged pixel whose flicker stopped is released when a later scan reads its events (here they
    switch every 4 ms: not a mains period)."""
    ev = _events(_flicker(2, 1, 10_000, 0, 60_000) + [(t, 2, 1, k % 2 == 0) for k, t in
                                                       enumerate(range(fpm.IDLE_PERIOD_US, 2 * fpm.IDLE_PERIOD_US,
                                                                       2_000))])
    fp = FlickerPixels(W, H)
    got = [(int(ev["t"][k]), None if m is None else bool(m[1, 2])) for k, m, f in fp.steps(ev)]
    assert [m for t, m in got] == [True, False], got
    assert fpm.IDLE_PERIOD_US <= got[1][0] <= fpm.IDLE_PERIOD_US + fpm.SCAN_US, got


@pytest.mark.parametrize("period_us", [8_333, 10_000, 20_000, 22_000])
@pytest.mark.parametrize("on_after_scan_end_us", [-15_000, 1_000])
def test_a_lamp_coming_into_view_is_flagged_within_the_documented_reaction_time(period_us, on_after_scan_end_us):
    """The module docstring's bound: one idle period plus two cycles, at most ~0.45 s, also at 50 Hz (a lamp
    flickering at the mains frequency) and at twice the longest mains period (a pixel missing every other switch),
    for a lamp that comes on just before a scan ends (too late for two cycles in it) or just after."""
    on_at = fpm.IDLE_PERIOD_US + fpm.SCAN_US + on_after_scan_end_us
    ev = _events([(0, 0, 0, True)] + _flicker(2, 1, period_us, on_at, on_at + fpm.IDLE_PERIOD_US + 100_000))
    fp = FlickerPixels(W, H)
    flagged_at = next(int(ev["t"][k]) for k, m, f in fp.steps(ev) if 1 * W + 2 in f.tolist())
    assert 0 < flagged_at - on_at <= 450_000, (flagged_at, on_at)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cuts_at_random_places_and_empty_reads_do_not_change_the_result(seed):
    """Chunking independence with what the idle scans skip: a small lamp held across skipped ranges, a flag found
    in a scan's last span, events exactly at the phase boundaries, a pause longer than a period, empty reads;
    steps() and observe() alike."""
    origin, rng = 5_000, np.random.default_rng(seed)
    at = [origin + k * fpm.IDLE_PERIOD_US + d for k in range(5) for d in (0, fpm.SCAN_US)]  # phase boundaries
    rows = ([(t, 7, 3, True) for t in at] + [r for r in _noise(2 * fpm.IDLE_PERIOD_US, seed) if r[1:3] != (4, 2)]
            + _flicker(1, 1, 10_000, 0, 2 * fpm.IDLE_PERIOD_US)  # a small lamp, held across the skipped ranges
            + [r for r in _flicker(2, 1, 10_000, origin + fpm.SCAN_US - 30_600, origin + fpm.SCAN_US)]
            # its third switch exactly at the scan's end: not in the scan, so never read
            + [r for r in _flicker(4, 2, 10_000, at[1] - 30_000, at[1] + 1) if r[0] <= at[1]]
            + _flicker(3, 2, 20_000, 4 * fpm.IDLE_PERIOD_US, 5 * fpm.IDLE_PERIOD_US))  # after a pause
    ev = _events([(origin, 0, 0, True)] + [r for r in rows if r[0] > origin])
    at_boundary = np.flatnonzero(np.isin(ev["t"], at)) + 1  # reads that end exactly at a boundary, too
    cuts = np.sort(np.concatenate([rng.integers(0, ev.size + 1, 60), at_boundary, [0, ev.size // 2, ev.size // 2]]))
    pieces = np.split(ev, cuts)  # with empty pieces where cuts repeat

    def steps(parts):
        fp, out, base = FlickerPixels(W, H), [], 0
        for p in parts:
            out += [(base + k, None if m is None else np.flatnonzero(m).tolist(), f.tolist())
                    for k, m, f in fp.steps(p)]
            base += p.size
        return out

    def observe(parts):
        fp = FlickerPixels(W, H)
        return [q for p in parts for q in fp.observe(p)[1].tolist()]

    whole = steps([ev])
    assert steps(pieces) == whole and len(whole) >= 3
    assert all(2 * W + 4 not in f for k, m, f in whole if ev["t"][k] < at[2])
    assert observe(pieces) == observe([ev]) and observe([ev])


def test_a_small_lamp_does_not_bloom_in_the_latent_image_at_each_scan():
    """What the hold across skipped ranges is for, seen in the reconstructor: a small lamp's halo (4 ON, 1 OFF
    event a cycle) must not climb in the latent image when the next scan starts reading it again."""
    from edi_live.datatypes import Frame
    from edi_live.reconstructor import EdiReconstructor

    lamp = [(1, 1), (2, 1), (3, 1)]
    rows = []
    for x, y in lamp:
        for k in range(130):  # 1.3 s at 100 Hz
            t = 1_000 + k * 10_000
            rows += [(t + 100 * j, x, y, True) for j in range(4)] + [(t + 5_000, x, y, False)]
    ev = _events(rows)
    rec = EdiReconstructor(W, H, c=0.2)
    rec.on_frame(Frame(np.full((H, W), 100, np.uint8), -2000, -1000), _events([]))
    reference = rec.latent_log_image[1, 2]
    second_scan = ev["t"] >= fpm.IDLE_PERIOD_US + 1_000  # the periods count from the first event, at 1 ms
    rec.on_events(ev[~second_scan])
    assert rec.stats()["flicker_pixels"] == len(lamp) and rec.latent_log_image[1, 2] == reference
    for a in range(int(np.count_nonzero(~second_scan)), ev.size, 20):  # the first 30 ms of the second scan
        if ev["t"][a] > fpm.IDLE_PERIOD_US + 30_000:
            break
        rec.on_events(ev[a:a + 20])
        assert rec.latent_log_image[1, 2] == reference, int(ev["t"][a])
