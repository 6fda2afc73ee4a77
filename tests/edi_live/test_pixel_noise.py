"""Per-pixel noise rates (edi_live.pixel_noise), estimated by the reconstructor from its frame pairs: recovered on
still scenes with known rates (the simulator's light-dependent shot noise; a synthetic stream with different ON
and OFF rates), not inflated by a moving edge, reported in the stats, kept by a saved calibration and refused for
another camera; the compiled update does what its numpy reference does."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live import calibration
from edi_live.config import EdiConfig
from edi_live.datatypes import EVENT_DTYPE, Frame, SourceInfo
from edi_live.errors import ConfigError
from edi_live.pixel_noise import NoiseRates, PixelNoise, update_still_counts
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate
from edi_live.stats import format_status, format_summary


def _run(width: int, height: int, events: np.ndarray, frames: list, **settings) -> EdiReconstructor:
    """Events and frames in the order the worker hands them over."""
    rec = EdiReconstructor(width, height, **settings)
    t = events["t"]
    fed = 0
    for frame in frames:
        end = int(np.searchsorted(t, frame.exposure_end_us, side="right"))
        rec.on_events(events[fed:end])
        fed = end
        rec.on_frame(frame, events[int(np.searchsorted(t, frame.exposure_start_us)):end])
    return rec


def _still_noise_scene(seed: int = 3):
    """A still scene whose pixels fire 2 Hz of background plus shot noise of up to 20 Hz in the dark."""
    cfg = SceneConfig(width=80, height=60, duration_s=6.0, velocity_px_s=(0.0, 0.0), noise_rate_hz=2.0,
                      shot_noise_hz=20.0, frame_interval_us=40_000, exposure_us=20_000, seed=seed)
    sim = simulate(cfg)
    intensity = sim.gt_images[0] / 255.0
    truth = cfg.noise_rate_hz + cfg.shot_noise_hz * np.minimum(1.0, cfg.shot_noise_dark / intensity)
    return sim, truth  # truth: ON + OFF Hz per pixel; the simulator draws each polarity with probability 1/2


def test_still_scene_rates_are_recovered_per_pixel_on_and_off():
    sim, truth = _still_noise_scene()
    rec = _run(80, 60, sim.events, sim.frames)
    rates = rec.noise_rates()
    assert rates is not None and rates.shape == (60, 80)
    assert np.median(rates.seconds) > 5.0  # nearly the whole run counts as still
    quartiles = np.quantile(truth, [0, 0.25, 0.5, 0.75, 1.0])
    for est in rates.estimate():
        # per pixel: ~18-40 events of each polarity per pixel, so Poisson alone gives ~20 % per pixel
        assert np.median(np.abs(est / (truth / 2) - 1)) < 0.2
        for lo, hi in zip(quartiles[:-1], quartiles[1:]):  # by true rate: no bias beyond the prior's pull (12 %)
            px = (truth >= lo) & (truth <= hi)
            assert abs(est[px].mean() / (truth[px].mean() / 2) - 1) < 0.12, (lo, hi)
    s = rec.stats()
    assert s["noise_hz_p50"] == pytest.approx(np.median(truth), rel=0.1)
    assert s["noisy_pixels"] == 0  # the rates vary 5x with the light, smoothly; nothing is an outlier


def _poisson_events(rng, on_hz: np.ndarray, off_hz: np.ndarray, t0: int, t1: int) -> np.ndarray:
    h, w = on_hz.shape
    parts = []
    for rate, pol in ((on_hz, True), (off_hz, False)):
        n = rng.poisson(rate.reshape(-1) * (t1 - t0) * 1e-6)
        pix = np.repeat(np.arange(h * w), n)
        ev = np.zeros(pix.size, EVENT_DTYPE)
        ev["t"], ev["x"], ev["y"], ev["p"] = rng.integers(t0, t1, pix.size), pix % w, pix // w, pol
        parts.append(ev)
    ev = np.concatenate(parts)
    return ev[np.argsort(ev["t"], kind="stable")]


def test_on_and_off_rates_are_told_apart_and_a_noisy_pixel_is_found():
    """ON rates grow along x (1-9 Hz), OFF rates along y (0.5-2.5 Hz); one pixel fires 60 Hz ON."""
    w, h = 40, 30
    rng = np.random.default_rng(7)
    on_hz = np.tile(np.linspace(1.0, 9.0, w), (h, 1))
    off_hz = np.tile(np.linspace(0.5, 2.5, h)[:, None], (1, w))
    on_hz[12, 20] = 60.0
    events = _poisson_events(rng, on_hz, off_hz, 0, 16_000_000)
    image = np.full((h, w), 120, np.uint8)
    frames = [Frame(image, k * 40_000 + 10_000, k * 40_000 + 30_000) for k in range(399)]
    rec = _run(w, h, events, frames)
    rates = rec.noise_rates()
    assert rates is not None
    est_on, est_off = rates.estimate()
    for est, truth in ((est_on, on_hz), (est_off, off_hz)):
        typical = np.ones((h, w), bool)
        typical[12, 20] = False
        assert np.median(np.abs(est[typical] / truth[typical] - 1)) < 0.2
    # the gradients themselves, averaged over the other axis, within 15 % (the prior pulls a 1 Hz column a few %
    # towards the 5 Hz of the whole sensor)
    np.testing.assert_allclose(np.delete(est_on, 12, axis=0).mean(axis=0), on_hz[0], rtol=0.15)
    np.testing.assert_allclose(np.delete(est_off, 20, axis=1).mean(axis=1), off_hz[:, 0], rtol=0.15)
    assert est_on[12, 20] == pytest.approx(60.0, rel=0.15)
    assert rec.stats()["noisy_pixels"] == 1


def _sweeping_edges(rng, w: int, h: int, noise_hz: float, speed_px_s: float, duration_us: int):
    """A sharp vertical edge (3 thresholds of contrast) sweeps left to right again and again over a still
    background: each pixel fires 3 ON events within 0.5 ms when the edge reaches its column; plus Poisson noise
    (noise_hz per pixel, even polarity). APS frames (20 ms exposure every 40 ms) show the edge blurred over the
    exposure. Returns (events, frames, whether each event is noise)."""
    sweep_us = int(w / speed_px_s * 1e6)
    edge_t = []  # (t, x)
    for start in range(0, duration_us - sweep_us, 2 * sweep_us):  # a sweep, then as long still
        edge_t += [(start + int(x / speed_px_s * 1e6), x) for x in range(w)]
    rows = [(t + 150 * k + int(rng.integers(0, 100)), x, y) for t, x in edge_t for y in range(h) for k in range(3)]
    sig = np.zeros(len(rows), EVENT_DTYPE)
    sig["t"], sig["x"], sig["y"] = np.array(rows).T
    sig["p"] = True
    noise = _poisson_events(rng, np.full((h, w), noise_hz / 2), np.full((h, w), noise_hz / 2), 0, duration_us)
    events = np.concatenate([sig, noise])
    is_noise = np.concatenate([np.zeros(sig.size, bool), np.ones(noise.size, bool)])
    order = np.argsort(events["t"], kind="stable")
    frames = []
    for k in range(duration_us // 40_000 - 1):
        ts, te = k * 40_000 + 10_000, k * 40_000 + 30_000
        bright = np.zeros((h, w))
        for t in np.linspace(ts, te, 21):  # the edge's column over the exposure: bright to its left
            phase = t % (2 * sweep_us)
            bright[:, : int(min(phase, sweep_us) / sweep_us * w) if phase < sweep_us else 0] += 1 / 21
        frames.append(Frame((40 + 140 * bright).astype(np.uint8), ts, te))
    return events[order], frames, is_noise[order]


def test_a_moving_edge_does_not_inflate_the_rates_of_the_pixels_it_crosses():
    w, h = 60, 40
    events, frames, is_noise = _sweeping_edges(np.random.default_rng(2), w, h, 2.0, 120.0, 12_000_000)
    naive = np.bincount(events["y"].astype(np.int64) * w + events["x"], minlength=w * h) / 12.0
    assert np.median(naive) > 2.2 * 2.0  # counting every event: the edge adds 3 Hz of ON events
    on, off = _run(w, h, events, frames).noise_rates().estimate()
    assert np.median(on + off) == pytest.approx(2.0, rel=0.15)
    assert np.percentile(on + off, 99) < 2.5 * 2.0
    assert np.median(on) == pytest.approx(np.median(off), rel=0.2)  # the edge's ON events stay out


def test_textured_motion_inflates_the_rates_a_little_not_like_counting_every_event():
    """Moving blocks: low-contrast texture fires single events at pixels whose neighbours stay quiet and whose
    APS hardly changes (a threshold crossing from a residual); they look like noise and leak in (~+40 %), far
    below what counting every event gives (8x)."""
    cfg = SceneConfig(width=80, height=60, duration_s=3.0, velocity_px_s=(120.0, 30.0), noise_rate_hz=2.0,
                      frame_interval_us=40_000, exposure_us=20_000, seed=5, ground_truth=False, aps_noise_dn=1.0)
    sim = simulate(cfg)
    naive = np.bincount(sim.events["y"].astype(np.int64) * 80 + sim.events["x"], minlength=80 * 60) / 3.0
    assert np.median(naive) > 5 * cfg.noise_rate_hz
    on, off = _run(80, 60, sim.events, sim.frames).noise_rates().estimate()
    assert np.median(on + off) < 1.6 * cfg.noise_rate_hz


def test_a_still_interval_is_judged_apart_from_the_pixels_own_events():
    """The reference and the kernel agree, and a pixel's own burst never makes its interval "busy"."""
    h, w = 9, 11
    rng = np.random.default_rng(1)
    n_on, n_off = rng.poisson(0.3, h * w), rng.poisson(0.3, h * w)
    n_on[4 * w + 5] = 50  # a noisy pixel in a quiet neighbourhood
    b_prev = rng.uniform(0, 255, (h, w)).astype(np.float32)
    b_cur = b_prev + rng.normal(0, 6, (h, w)).astype(np.float32)
    masked = np.zeros((h, w), bool)
    masked[0, 0] = True
    out = []
    for reference in (False, True):
        acc = [np.full((h, w), 2.0) for _ in range(3)]
        args = dict(neighbour_events=2, aps_tolerance_dn=4.0, aps_tolerance_rel=0.1, decay=0.5, interval_s=0.04)
        if reference:
            with edi.numpy_reference():
                n = update_still_counts(*acc, n_on, n_off, b_prev, b_cur, masked, **args)
        else:
            n = update_still_counts(*acc, n_on, n_off, b_prev, b_cur, masked, **args)
        out.append((n, acc))
    assert out[0][0] == out[1][0] > 0
    for a, b in zip(out[0][1], out[1][1]):
        np.testing.assert_array_equal(a, b)
    # the oracle, written out: neighbours' events (8-neighbourhood) and the APS change
    n = (n_on + n_off).reshape(h, w)
    pad = np.pad(n, 1)
    neighbours = sum(pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) - n
    still = (neighbours <= 2) & (np.abs(b_cur - b_prev) <= 4.0 + 0.1 * np.maximum(b_prev, b_cur)) & ~masked
    np.testing.assert_array_equal(out[0][1][2], np.where(still, 1.0 + 0.04, 1.0))
    assert out[0][1][0][4, 5] == (1.0 + 50 if still[4, 5] else 1.0)


def test_given_rate_and_off():
    w, h = 16, 12
    fixed = PixelNoise(w, h, fixed_hz=3.0)
    assert fixed.summary()["noise_hz_p50"] == 3.0 and fixed.rates() is None  # a setting, not a calibration
    off = EdiReconstructor(w, h, noise_stats=False)
    assert "noise_hz_p50" not in off.stats() and off.noise_rates() is None
    with pytest.raises(ConfigError):
        EdiReconstructor(w, h, noise_rate_hz=-1.0)


def test_status_line_and_summary_show_the_noise_figures():
    s = {"noise_hz_p50": 0.52, "noise_hz_p99": 7.1, "noise_on_hz_p50": 0.3, "noise_off_hz_p50": 0.22,
         "noisy_pixels": 12, "c_on": 0.2, "c_off": 0.2}
    assert "noise 0.52/7.1 Hz (12 noisy)" in format_status(s)
    summary = format_summary(s, 1.0)
    assert "noise per pixel 0.52 Hz median (ON 0.3, OFF 0.22), 7.1 Hz p99, 12 noisy pixels" in summary
    assert "noise" not in format_status({"c_on": 0.2, "c_off": 0.2})


def _info(serial: str = "00000391", w: int = 80, h: int = 60) -> SourceInfo:
    return SourceInfo(w, h, "DAVIS346", serial)


def test_saved_rates_round_trip_and_start_the_next_run(tmp_path):
    sim, _ = _still_noise_scene(seed=4)
    rec = _run(80, 60, sim.events, sim.frames)
    rates = rec.noise_rates()
    cal = calibration.from_stats(_info(), {"c_on": 0.2, "c_off": 0.2}, rates)
    path = tmp_path / "cal.json"
    calibration.save(cal, path)
    back = calibration.load(path)
    assert back.noise is not None
    for a, b in ((rates.on_hz, back.noise.on_hz), (rates.off_hz, back.noise.off_hz),
                 (rates.seconds, back.noise.seconds)):
        np.testing.assert_allclose(b, a, rtol=1e-3, atol=1e-4)  # float16: three significant digits
    edi_cfg, _ = calibration.prepare(EdiConfig(), _info(), path, None)
    np.testing.assert_array_equal(edi_cfg.start.noise.on_hz, back.noise.on_hz)
    started = EdiReconstructor(80, 60, noise_start=edi_cfg.start.noise)
    for a, b in zip(started.noise_rates().estimate(), rates.estimate()):  # before any frame: the saved estimate
        np.testing.assert_allclose(a, b, rtol=2e-3)
    assert started.stats()["noise_hz_p50"] == pytest.approx(float(np.median(sum(rates.estimate()))), rel=2e-3)


def test_a_calibration_of_another_camera_or_size_is_refused(tmp_path):
    noise = NoiseRates(*(np.ones((60, 80), np.float32) for _ in range(3)))
    path = tmp_path / "other.json"
    calibration.save(calibration.Calibration("DAVIS346_00000104", 80, 60, 0.2, 0.2, noise=noise), path)
    with pytest.raises(ConfigError, match="is for DAVIS346_00000104"):
        calibration.prepare(EdiConfig(), _info(), path, None)
    with pytest.raises(ConfigError, match="is for"):
        calibration.prepare(EdiConfig(), _info("00000104", 346, 260), path, None)


def test_defective_noise_arrays_are_refused_with_one_line(tmp_path):
    import json

    noise = NoiseRates(*(np.ones((60, 80), np.float32) for _ in range(3)))
    path = tmp_path / "cal.json"
    calibration.save(calibration.Calibration("DAVIS346_00000391", 80, 60, 0.2, 0.2, noise=noise), path)
    data = json.loads(path.read_text())
    data["noise"]["shape"] = [61, 80]
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="noise rates"):
        calibration.load(path)
    data["noise"]["shape"] = [60, 80]
    data["noise"]["on_hz"] = "not base64!"
    path.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match="noise rates 'on_hz' cannot be read"):
        calibration.load(path)


def test_the_noise_flags_and_toml_keys_reach_the_reconstructor():
    from edi_live.cli import options_from_args
    from edi_live.config import NodeConfig
    from edi_live.node import default_reconstructor

    def reconstructor(*argv: str) -> EdiReconstructor:
        flags, _ = options_from_args(["--replay", "x.aedat4", *argv])
        return default_reconstructor(16, 12, NodeConfig.from_options(flags).edi)

    assert reconstructor().settings.noise_stats is True
    assert "noise_hz_p50" not in reconstructor("--no-noise-stats").stats()
    assert reconstructor("--noise-rate-hz", "0.5").stats()["noise_hz_p50"] == 0.5
    toml = NodeConfig.from_options({"replay": "x.aedat4", "noise_stats": False, "noise_rate_hz": 2})
    assert toml.edi.noise_stats is False and toml.edi.noise_rate_hz == 2
    with pytest.raises(ConfigError, match="noise-stats must be true or false"):
        NodeConfig.from_options({"replay": "x.aedat4", "noise_stats": "no"})  # a TOML string, not a boolean
    with pytest.raises(ConfigError, match="noise-rate-hz must be a rate"):
        NodeConfig.from_options({"replay": "x.aedat4", "noise_rate_hz": -1})


def _summary_reference(noise: PixelNoise) -> dict:
    """The summary as first written: numpy's selection percentile and median on the unsorted rates."""
    from edi_live.pixel_noise import noisy_pixels, pooled_rate, shrunk_rate

    on_c, off_c, sec = noise._on, noise._off, noise._seconds
    g_on, g_off = pooled_rate(on_c, sec), pooled_rate(off_c, sec)
    on, off = shrunk_rate(on_c, sec, g_on, noise.prior_s), shrunk_rate(off_c, sec, g_off, noise.prior_s)
    p50, p99 = np.percentile(on + off, [50, 99])
    noisy = noisy_pixels(on_c + off_c, sec, g_on + g_off, noise.noisy_factor, noise.prior_s)
    return {"noise_hz_p50": round(float(p50), 3), "noise_hz_p99": round(float(p99), 3),
            "noise_on_hz_p50": round(float(np.median(on)), 3), "noise_off_hz_p50": round(float(np.median(off)), 3),
            "noisy_pixels": int(np.count_nonzero(noisy))}


@pytest.mark.parametrize("case", ["one_pixel", "odd", "even", "constant", "extremes", "one_seen"])
def test_summary_percentiles_match_numpy_on_the_unsorted_rates(case):
    """The summary takes its percentiles from sorted copies (faster); the figures must be numpy's own on the
    unsorted rates, at odd and even pixel counts (the median's two middle values), ties and extremes."""
    rng = np.random.default_rng(len(case))
    h, w = {"one_pixel": (1, 1), "odd": (3, 5), "even": (26, 34)}.get(case, (12, 9))
    on = rng.gamma(0.5, 0.4, (h, w)).astype(np.float32)
    off = rng.gamma(0.5, 0.3, (h, w)).astype(np.float32)
    sec = rng.uniform(0.1, 60.0, (h, w)).astype(np.float32)
    if case == "constant":
        on[:], off[:], sec[:] = 0.25, 0.25, 10.0
    if case == "extremes":
        on.reshape(-1)[::3], off.reshape(-1)[1::4], sec.reshape(-1)[::5] = 1e6, 0.0, 1e-6
    if case == "one_seen":
        sec[:] = 0.0
        sec[0, 0] = 2.0
    noise = PixelNoise(w, h, start=NoiseRates(on, off, sec))
    assert noise.summary() == _summary_reference(noise)
    n_on = rng.poisson(0.3, h * w)
    noise.update(n_on, np.zeros(h * w, np.int64), np.full((h, w), 100.0, np.float32),
                 np.full((h, w), 100.0, np.float32), 40_000)
    noise._refresh()
    assert noise.summary() == _summary_reference(noise)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_of_sorted_is_numpys_median_bit_for_bit(dtype):
    from edi_live.pixel_noise import median_of_sorted

    rng = np.random.default_rng(5)
    cases = [np.array([3.5]), np.array([1.0, 2.0]), np.array([0.1, 0.2]), np.full(6, 0.3), np.full(7, 0.3),
             np.array([0.0, 1e30, 1e30, 3e38]), np.array([np.float32(16777216.0), np.float32(16777217.0)])]
    cases += [rng.gamma(0.5, 0.2, n) for n in (2, 3, 1000, 1001, 89960)]
    cases += [np.round(rng.gamma(0.5, 0.2, 5000), 2)]  # many ties, as a real sensor's rates have
    cases += [np.array([1.0, np.nan, 2.0]), np.array([np.nan, 0.5, 0.7, 0.9]), np.array([np.nan])]  # numpy: NaN
    for values in cases:
        values = np.asarray(values, dtype)
        got = median_of_sorted(np.sort(values))
        want = np.median(values)
        assert got.dtype == want.dtype and (got.tobytes() == want.tobytes() or np.isnan(got) and np.isnan(want)), \
            (values[:4], got, want)
    with pytest.warns(RuntimeWarning):  # no values: NaN, as numpy's median gives
        assert np.isnan(median_of_sorted(np.zeros(0, dtype)))


def _noise_updates(seed: int, n: int, h: int = 20, w: int = 30):
    """n frame pairs of Poisson counts on a still APS image, busy enough that the neighbour limit follows the
    sensor-wide rate (λ over 8 neighbours well above 2)."""
    rng = np.random.default_rng(seed)
    b = np.full((h, w), 120.0, np.float32)
    rate = rng.gamma(2.0, 4.0, h * w)  # Hz per pixel and polarity, a tail of noisier pixels
    for _ in range(n):
        yield rng.poisson(rate * 0.05), rng.poisson(rate * 0.05), b, b, 50_000


def test_summary_is_current_when_asked_and_asking_changes_no_estimate():
    """The summary is computed when the stats ask for it, from the counts as they stand (not those of up to 25
    pairs before) when asked for a current one, and asking for it, on any schedule, leaves the estimate itself
    (the still test reads the sensor-wide rates) as it would be without asking."""
    asked, quiet = PixelNoise(30, 20), PixelNoise(30, 20)
    for k, pair in enumerate(_noise_updates(8, 61)):
        asked.update(*pair)
        quiet.update(*pair)
        if k % 3 == 0:
            asked.summary()
    assert asked.updates == 61  # between two refreshes of the sensor-wide rates (every 25)
    assert quiet.summary(current=True) == _summary_reference(quiet)
    assert asked.summary(current=True) == _summary_reference(asked)
    for a, b in zip(dataclasses.astuple(asked.rates()), dataclasses.astuple(quiet.rates())):
        np.testing.assert_array_equal(a, b)


def test_the_summary_is_refreshed_at_most_once_per_summary_every_updates_unless_asked_for_a_current_one():
    """The node's stats message asks every second; each refresh is a few ms of percentiles over every pixel, which
    on a still scene was most of the publisher thread's CPU. Between refreshes the figure stays as it was; at the
    end of a run (current=True) it is brought up to date."""
    noise = PixelNoise(30, 20, summary_every=10)
    pairs = _noise_updates(9, 25)
    noise.update(*next(pairs))
    first = noise.summary()
    assert first == _summary_reference(noise)  # the first figure as soon as there is one
    for _ in range(9):
        noise.update(*next(pairs))
        assert noise.summary() == first  # 9 updates later: not yet
    noise.update(*next(pairs))
    assert noise.summary() == _summary_reference(noise) != first  # the 10th: refreshed
    noise.update(*next(pairs))
    stale = noise.summary()
    assert stale != _summary_reference(noise)
    assert noise.summary(current=True) == _summary_reference(noise)
