"""The word decoder against hand-built word streams (expected values worked out from the protocol note, not
from the code) and against the encoder on random recordings, in random chunkings; the numba kernel against
its numpy reference."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.davis import _kernel
from drivers.davis.decoder import DavisDecoder
from drivers.davis.encoder import WordEncoder
from tests.helpers.recordings import flatten, random_recording

TS, Y, XOFF, XON, WRAP, SAMPLE = 0x8000, 0x1000, 0x2000, 0x3000, 0x7000, 0x4000


def _decode(words, chunks=None, **kw):
    d = DavisDecoder(kw.pop("cols", 346), kw.pop("rows", 260), **kw)
    data = np.asarray(words, dtype="<u2").tobytes()
    chunks = chunks or [len(data)]
    out, pos = [], 0
    for n in chunks:
        out.append(d.decode(data[pos:pos + n]))
        pos += n
    if pos < len(data):
        out.append(d.decode(data[pos:]))
    return d, out


def _tuples(events):
    return [(int(e["t"]), int(e["x"]), int(e["y"]), bool(e["p"])) for e in events]


def test_wrap_multiplier_and_polarity():
    words = [TS | 100, Y | 5, XOFF | 7, XON | 8, WRAP | 3, TS | 10, Y | 2, XON | 9]
    _, out = _decode(words, time_offset_us=1000)
    assert _tuples(flatten(out)[0]) == [(1100, 7, 5, False), (1100, 8, 5, True), (1000 + 3 * 32768 + 10, 9, 2, True)]


def test_out_of_range_addresses_are_dropped_and_counted():
    # Y 300 >= 260 rows is ignored (last row stays 4); X 400 >= 346 columns is dropped
    words = [TS | 1, Y | 4, Y | 300, XON | 3, XON | 400, XOFF | 5]
    d, out = _decode(words)
    assert _tuples(flatten(out)[0]) == [(1, 3, 4, True), (1, 5, 4, False)]
    assert d.counters["bad_words"] == 2


def test_timestamp_reset_keeps_time_monotonic_and_marks_gap():
    words = [TS | 500, Y | 1, XON | 1, TS | 900, Y | 2, XON | 3, 0x0001, TS | 50, Y | 4, XOFF | 6]
    d, out = _decode(words)
    assert [e[0] for e in _tuples(flatten(out)[0])] == [500, 900, 950]
    assert out[0].gap and d.counters["timestamp_resets"] == 1
    assert out[0].triggers["type"].tolist() == [0] and out[0].triggers["t"].tolist() == [900]


def _frame_words(reset, signal, t_start=10, t_exp_end=40):
    """2x2 global-shutter frame, column-wise (A[col][row]), ROI 0..1 x 0..1."""
    roi = []
    for v in (0, 0, 1, 1):
        roi += [0x5100 | (v >> 8), 0x5200 | (v & 0xFF)]
    w = [TS | t_start, 8] + roi
    for c in range(2):
        w += [11] + [SAMPLE | reset[c][r] for r in range(2)] + [13]
    w += [14, TS | t_exp_end, 15]
    for c in range(2):
        w += [12] + [SAMPLE | signal[c][r] for r in range(2)] + [13]
    return w + [TS | t_exp_end + 5, 10]


def test_aps_cds_white_rule_and_exposure_times():
    # pixel (x,y): (0,0) 1000-400 = 600; (0,1) reset 300 < 384 -> white; (1,0) signal 0 -> white; (1,1) clamps to 0
    words = _frame_words(reset=[[1000, 300], [900, 500]], signal=[[400, 100], [0, 700]])
    _, out = _decode(words, cols=2, rows=2, frame_bits=16)
    (f,) = flatten(out)[1]
    assert f.image.tolist() == [[600 << 6, 1023 << 6], [1023 << 6, 0]]
    assert (f.exposure_start_us, f.exposure_end_us, f.start_us, f.end_us) == (10, 40, 10, 45)


def test_davis240_samples_are_doubled():
    words = _frame_words(reset=[[500, 150], [450, 250]], signal=[[200, 50], [0, 350]])
    _, out = _decode(words, cols=2, rows=2, frame_bits=16, adc_x2=True)
    assert flatten(out)[1][0].image.tolist() == [[600 << 6, 1023 << 6], [1023 << 6, 0]]


@pytest.mark.parametrize("orientation,expected", [
    (0, [[600, 200], [1023, 0]]),   # image[y][x] = A[x][y]
    (2, [[200, 600], [0, 1023]]),   # flip X: column count runs right to left
    (1, [[1023, 0], [600, 200]]),   # flip Y: row count runs bottom to top
    (4, [[600, 1023], [200, 0]]),   # swap: image[x][y] = A[x][y]
    (7, [[0, 200], [1023, 600]]),   # all three
])
def test_aps_orientation(orientation, expected):
    # readout matrix A[column][row] = [[600, 1023 (white)], [200, 0]]
    words = _frame_words(reset=[[1000, 300], [900, 500]], signal=[[400, 100], [700, 700]])
    _, out = _decode(words, False, cols=2, rows=2, frame_bits=16, aps_orientation=orientation)
    assert (flatten(out)[1][0].image >> 6).tolist() == expected


def test_missing_column_end_drops_the_frame():
    good = _frame_words(reset=[[1000, 1000], [1000, 1000]], signal=[[500, 500], [500, 500]])
    bad = list(good)
    bad.remove(13)  # first reset column never ends
    d, out = _decode(bad + good, cols=2, rows=2)
    frames = flatten(out)[1]
    assert len(frames) == 1 and d.counters["frames_dropped"] == 1
    assert frames[0].image.tolist() == [[125, 125], [125, 125]]  # (1000-500) >> 2


def _imu_words(vals, cfg=0xE0 | (1 << 2) | 1):
    w = [TS | 77, 5, 0x5300 | cfg]
    for v in vals:
        v &= 0xFFFF
        w += [0x5000 | (v >> 8), 0x5000 | (v & 0xFF)]
    return w + [7]


@pytest.mark.parametrize("flip,sign", [(0, 1.0), (4, -1.0)])
def test_imu_scaled_to_physical_units(flip, sign):
    # +-4 g -> 8192 LSB/g, +-500 dps -> 65.536 LSB/(deg/s), temperature raw/340 + 35 (MPU-6050)
    _, out = _decode(_imu_words([8192, -8192, 4096, 340, 6554, 0, -6554]), imu_orientation=flip)
    (s,) = flatten(out)[2]
    assert s["t"] == 77
    np.testing.assert_allclose(s["accel_g"], [sign * 1.0, -1.0, 0.5], rtol=1e-6)
    np.testing.assert_allclose(s["gyro_dps"], [sign * 6554 / 65.536, 0.0, -6554 / 65.536], rtol=1e-6)
    assert s["temperature_c"] == pytest.approx(36.0)


def test_incomplete_imu_sample_is_discarded():
    words = _imu_words([1, 2, 3, 4, 5, 6, 7])
    del words[5:7]
    _, out = _decode(words, False)
    assert len(flatten(out)[2]) == 0


@pytest.mark.parametrize("model", ["davis346", "davis240"])
@pytest.mark.parametrize("orientation", range(8))
def test_encoder_decoder_round_trip(rng, model, orientation):
    w, h, x2 = (346, 260, False) if model == "davis346" else (240, 180, True)
    packets = random_recording(rng, w, h, n_events=5000, n_frames=2, n_imu=5)
    enc = WordEncoder(w, h, dvs_orientation=orientation & 4, aps_orientation=orientation, adc_x2=x2)
    t0 = packets[0].events["t"][0]
    ev, frames, imu = flatten(packets)
    blocks = sorted([(f.exposure_start_us, 0, "fs", f) for f in frames]
                    + [(f.exposure_end_us, 1, "fe", f) for f in frames]
                    + [(int(s["t"]), 1, "imu", s) for s in imu], key=lambda b: (b[0], b[1]))
    words, pos = [], 0
    for t, _, kind, obj in blocks:
        k = int(np.searchsorted(ev["t"], t, side="right"))
        words.append(enc.encode_events(ev["t"][pos:k] - t0, ev["x"][pos:k], ev["y"][pos:k], ev["p"][pos:k]))
        pos = k
        d = t - t0
        if kind == "fs":
            words.append(enc.encode_frame_start(d, obj))
        elif kind == "fe":
            words.append(enc.encode_frame_end(d, obj))
        else:
            words.append(enc.encode_imu(d, obj["accel_g"], obj["gyro_dps"], float(obj["temperature_c"])))
    words.append(enc.encode_events(ev["t"][pos:] - t0, ev["x"][pos:], ev["y"][pos:], ev["p"][pos:]))
    data = np.concatenate(words).tobytes()
    cuts = np.sort(rng.integers(0, len(data), 40))
    chunks = np.diff(np.concatenate([[0], cuts, [len(data)]])).tolist()
    cols, rows = (h, w) if orientation & 4 else (w, h)
    d, out = _decode(np.frombuffer(data, "<u2"), chunks=chunks, cols=cols, rows=rows,
                     dvs_orientation=orientation & 4, aps_orientation=orientation, adc_x2=x2, time_offset_us=int(t0))
    dev, dframes, dimu = flatten(out)
    assert np.array_equal(dev, ev)
    assert len(dframes) == len(frames)
    for a, b in zip(dframes, frames):
        assert a.image.shape == b.image.shape
        assert np.abs(a.image.astype(int) - b.image.astype(int)).max() <= (1 if x2 else 0)
        assert (a.exposure_start_us, a.exposure_end_us) == (b.exposure_start_us, b.exposure_end_us)
    np.testing.assert_allclose(dimu["accel_g"], imu["accel_g"], atol=1 / 8192)
    np.testing.assert_allclose(dimu["gyro_dps"], imu["gyro_dps"], atol=1 / 65.536)
    assert all(np.all(np.diff(p.events["t"]) >= 0) for p in out)


@pytest.mark.parametrize("latency_us", [0, 25_000])  # USB/host latency on top of up to 3 ms jitter
def test_gap_reanchors_wraps_from_arrival_times(rng, latency_us):
    # 2 s of events at ~1 event/100 us; chunks of 5 ms; drop 120 ms worth of chunks (3+ wraps lost)
    n = 20000
    t = np.sort(rng.integers(0, 2_000_000, n))
    x, y, p = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.random(n) < 0.5
    enc = WordEncoder(346, 260)
    d = DavisDecoder(346, 260)
    got, gaps = [], []
    bounds = list(range(0, 2_000_001, 5000))
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        k0, k1 = np.searchsorted(t, [lo, hi])
        words = enc.encode_events(t[k0:k1], x[k0:k1], y[k0:k1], p[k0:k1])
        arrival_ns = (hi + latency_us + int(rng.integers(0, 3000))) * 1000
        if 1_000_000 <= lo < 1_120_000:
            continue  # lost upstream
        if lo == 1_120_000:
            d.mark_gap()
        pkt = d.decode(words.tobytes(), arrival_ns)
        got.append(pkt.events)
        gaps.append(pkt.gap)
    ev = np.concatenate(got)
    keep = (t < 1_000_000) | (t >= 1_120_000)
    # after the gap, words before the chunk's first timestamp cannot be placed and are skipped
    assert sum(gaps) == 1
    tail = ev[ev["t"] >= 1_120_000]
    ref_t = t[keep]
    assert np.array_equal(ev["t"][: np.count_nonzero(t < 1_000_000)], t[t < 1_000_000])
    assert np.array_equal(tail["t"], ref_t[ref_t >= 1_120_000][-len(tail):])
    assert len(tail) >= np.count_nonzero(t >= 1_120_000) - 5


def test_garbage_words_never_break_ordering(rng):
    enc = WordEncoder(346, 260)
    t = np.sort(rng.integers(0, 500_000, 5000))
    words = enc.encode_events(t, rng.integers(0, 346, 5000), rng.integers(0, 260, 5000), rng.random(5000) < 0.5)
    noisy = np.insert(words, np.sort(rng.integers(0, len(words), 300)), rng.integers(0, 1 << 16, 300).astype(np.uint16))
    d, out = _decode(noisy, chunks=[1001] * (len(noisy) * 2 // 1001))
    ev = flatten(out)[0]
    assert len(ev) > 4000 and np.all(np.diff(ev["t"]) >= 0)
    assert all(p.watermark_us <= q.events["t"].min() for p, q in zip(out, out[1:]) if len(q.events))


def test_numba_kernel_agrees_with_the_numpy_reference_on_noise(rng):
    words = rng.integers(0, 1 << 16, 200_000).astype(np.uint16)
    words[rng.integers(0, len(words), 20)] = 1  # timestamp resets: the reference splits there
    results = []
    for fn in (_kernel.scan_numpy, _kernel.scan):
        st = _kernel.new_state(5)
        ev, ci, ct = fn(words, st, 346, 260, False)
        results.append((ev.copy(), ci.copy(), ct.copy(), st.copy()))
    for a, b in zip(*results):
        assert np.array_equal(a, b)


def test_dvs_words_interleaved_inside_a_readout(rng):
    # the device's multiplexer may put DVS row/column words between any two APS words
    frame = _frame_words(reset=[[1000, 300], [900, 500]], signal=[[400, 100], [700, 700]])
    words = list(frame)
    for pos in sorted(rng.integers(3, len(frame), 6).tolist(), reverse=True):
        words[pos:pos] = [Y | 3, XON | 4]
    _, out = _decode(words, cols=346, rows=260, frame_bits=16)
    ev, (f,) = flatten(out)[0], flatten(out)[1]
    assert len(ev) == 6 and set(zip(ev["x"].tolist(), ev["y"].tolist())) == {(4, 3)}
    assert (f.image >> 6).tolist() == [[600, 200], [1023, 0]]  # the 2x2 ROI the frame announced


def test_rolling_shutter_interleaved_reset_and_signal_columns():
    roi = []
    for v in (0, 0, 1, 1):
        roi += [0x5100 | (v >> 8), 0x5200 | (v & 0xFF)]
    reset, signal = [[1000, 300], [900, 500]], [[400, 100], [700, 700]]
    words = [TS | 5, 9] + roi
    for c in range(2):  # rolling shutter: each column's reset read is followed by its signal read
        words += [11] + [SAMPLE | reset[c][r] for r in range(2)] + [13]
        words += [12] + [SAMPLE | signal[c][r] for r in range(2)] + [13]
    words += [10]
    _, out = _decode(words, cols=2, rows=2, frame_bits=16)
    assert (flatten(out)[1][0].image >> 6).tolist() == [[600, 200], [1023, 0]]
