"""The live prediction score: what the node's output predicted of each APS frame, against the no-motion baseline.

Oracles: scenes built here whose blurry frames are exact time averages of known latent images, hand-computed
window averages, and an independent dense (1 µs per sample) integration of the held frames.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from edi_live.datatypes import EVENT_DTYPE, Frame, Reconstruction
from edi_live.quality import PSNR_CAP_DB, PredictionScore


def aps(image, start, end, seq=0) -> Frame:
    return Frame(np.asarray(image, np.uint8), int(start), int(end), seq=seq)


def rec(image, t, ref_t, kind="latent") -> Reconstruction:
    return Reconstruction(image=np.asarray(image, np.uint8), t_us=int(t), kind=kind, ref_t_us=int(ref_t),
                          exposure_start_us=0, exposure_end_us=0, c_on=0.2, c_off=0.2, n_events=0)


def events_at(pixels, t) -> np.ndarray:
    ev = np.zeros(len(pixels), EVENT_DTYPE)
    ev["t"] = t
    ev["y"] = [p[0] for p in pixels]
    ev["x"] = [p[1] for p in pixels]
    return ev


def psnr_by_hand(pred, target) -> float:
    mse = np.mean((np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2)
    return 10 * math.log10(255.0**2 / mse)


# ---- a moving bar: latent image L_j over step j (100 µs each); APS frame k exposes steps 10k and 10k+1

STEP, PERIOD, H, W = 100, 1000, 4, 6


def bar(j, bright):
    img = np.full((H, W), 40, np.int64)
    img[:, j % W] = bright
    return img


def run_bar_scene(bright, n_frames=6, predictor="true", score=None):
    """Feeds a PredictionScore in the causal worker's order: latent frames up to an exposure end, the APS frame,
    its deblurred frame, then the latent frames rendered from it. `predictor` "true" sends the true latent
    images, "still" repeats the last APS frame."""
    score = score or PredictionScore("causal")
    results, blurry = [], []
    last_b = None
    for k in range(n_frames):
        start = k * PERIOD
        for j in range(max(0, 10 * (k - 1) + 2), 10 * k + 2):  # steps after frame k-1's exposure, in its window
            if k == 0:
                break
            image = bar(j, bright) if predictor == "true" else last_b
            results += score.on_emitted(rec(image, j * STEP, (k - 1) * PERIOD + STEP))
        exact = (bar(10 * k, bright) + bar(10 * k + 1, bright)) / 2
        b = np.floor(exact + 0.5).astype(np.uint8)
        blurry.append(b)
        results += score.on_aps_frame(aps(b, start, start + 2 * STEP, seq=k))
        results += score.on_emitted(rec(b, start + STEP, start + STEP, kind="deblurred"))
        last_b = b
    results += score.finish()
    return results, blurry, score


def test_exact_prediction_reaches_the_cap_and_beats_no_motion():
    results, _, score = run_bar_scene(bright=200)  # (40 + 200) / 2 is an integer: B is the exact time average
    assert len(results) == 5 and all(r.scored and r.n_frames_used == 2 and r.coverage == 1.0 for r in results)
    for r in results:
        assert r.psnr_pred_db == PSNR_CAP_DB
        assert r.psnr_still_db < 20  # the bar moved 4 columns between frames
    s = score.stats()
    assert s["pred_psnr_db"] == PSNR_CAP_DB and s["pred_beats_still_frac"] == 1.0 and s["pred_frames_scored"] == 5


def test_true_latent_frames_beat_no_motion_when_the_blurry_frame_is_rounded():
    results, blurry, _ = run_bar_scene(bright=201)  # B = 120.5 at the bar's pixels, rounded to 121
    for r, b_prev, b in zip(results, blurry, blurry[1:]):
        assert 10 * math.log10(255**2 / 0.25) - 1e-9 <= r.psnr_pred_db < PSNR_CAP_DB  # off by at most 0.5 DN
        assert r.psnr_still_db == pytest.approx(psnr_by_hand(b_prev, b))
        assert r.psnr_pred_db > r.psnr_still_db + 20


def test_repeating_the_previous_frame_equals_the_baseline_exactly():
    results, _, score = run_bar_scene(bright=200, predictor="still")
    assert len(results) == 5
    for r in results:
        assert r.psnr_pred_db == r.psnr_still_db
    s = score.stats()
    assert s["pred_gain_db"] == 0.0 and s["pred_beats_still_frac"] == 0.0


def test_the_frames_own_deblurred_and_later_frames_are_excluded():
    a = np.full((2, 2), 50)
    b_prev = np.full((2, 2), 60)
    target = np.full((2, 2), 100)
    window = (1000, 2000)  # mid-exposure 1500

    def score_with(extra):
        s = PredictionScore()
        s.on_aps_frame(aps(b_prev, 0, 200))
        s.on_emitted(rec(a, 300, 100))  # from frame k's reference, in force over the whole window
        s.on_aps_frame(aps(target, *window))
        out = []
        for r in extra:
            out += s.on_emitted(r)
        return out + s.finish()

    honest_only = score_with([])[0]
    own = score_with([rec(target, 1500, 1500, "deblurred"), rec(target, 1800, 1500)])[0]
    as_if_honest = score_with([rec(target, 1500, 100, "deblurred")])[0]  # the same image, claimed from frame k
    assert honest_only.psnr_pred_db == pytest.approx(psnr_by_hand(a, target))
    assert own.psnr_pred_db == honest_only.psnr_pred_db and own.n_frames_used == 1
    # including it would have changed the score: half the window would be the target itself
    assert as_if_honest.psnr_pred_db == pytest.approx(psnr_by_hand((a + target) / 2, target))
    assert as_if_honest.psnr_pred_db > honest_only.psnr_pred_db + 5


def test_piecewise_constant_average_on_a_2x2_example():
    # window [1000, 2000]: A (t=500) holds 1000..1250, B (t=1250) 1250..1900, C (t=1900) 1900..2000, D after it
    A, B, C, D = [[10, 20], [30, 40]], [[50, 60], [70, 80]], [[90, 100], [110, 120]], [[255, 255], [255, 255]]
    # by hand: (A*250 + B*650 + C*100) / 1000
    expected = np.array([[(10 * 250 + 50 * 650 + 90 * 100) / 1000, (20 * 250 + 60 * 650 + 100 * 100) / 1000],
                         [(30 * 250 + 70 * 650 + 110 * 100) / 1000, (40 * 250 + 80 * 650 + 120 * 100) / 1000]])
    assert expected[0, 0] == 44.0 and expected[1, 1] == 74.0
    target = [[40, 60], [60, 80]]
    s = PredictionScore()
    s.on_aps_frame(aps([[5, 5], [5, 5]], 0, 100))
    for image, t in ((A, 500), (B, 1250), (C, 1900)):
        s.on_emitted(rec(image, t, 50))
    s.on_aps_frame(aps(target, 1000, 2000))
    (r,) = s.on_emitted(rec(D, 2100, 50))  # the first frame after the window completes it
    np.testing.assert_array_equal(s.last_prediction, expected)
    assert r.n_frames_used == 3 and r.coverage == 1.0
    assert r.psnr_pred_db == pytest.approx(psnr_by_hand(expected, target))
    assert r.psnr_still_db == pytest.approx(psnr_by_hand(np.full((2, 2), 5), target))


def test_active_pixels_are_those_with_events_since_the_previous_frame():
    prev = np.full((2, 3), 100)
    target = np.array([[150, 100, 100], [100, 100, 255]])  # (1, 2) saturated: never scored
    pred = np.array([[150, 90, 90], [100, 100, 200]])  # exact at the moving pixel, 10 DN off at two still ones
    s = PredictionScore()
    s.on_events(events_at([(1, 1)], 5))  # before the first APS frame: ignored
    s.on_aps_frame(aps(prev, 0, 100))
    s.on_emitted(rec(pred, 150, 50))
    s.on_events(events_at([(0, 0), (1, 2)], 300))
    s.on_aps_frame(aps(target, 1000, 1100))
    (r,) = s.finish()
    assert r.valid_px == 5 and r.active_px == 1
    assert r.psnr_pred_active_db == PSNR_CAP_DB
    assert r.psnr_still_active_db == pytest.approx(psnr_by_hand([100], [150]))
    valid = target < 255
    assert r.psnr_pred_db == pytest.approx(psnr_by_hand(pred[valid], target[valid]))
    assert s.stats()["pred_psnr_active_db"] == PSNR_CAP_DB


def test_a_still_scene_marks_no_pixels_and_events_before_the_frame_sent_still_count(monkeypatch):
    # the pixels with events are marked once a frame was sent since the previous APS frame (else the next APS frame
    # is not scored): a still scene's reads cost no marking, and the events before the frame sent still count
    import edi_live.edi as edi

    marked = []
    mark = edi.mark_event_pixels
    monkeypatch.setattr(edi, "mark_event_pixels", lambda ev, *a: (marked.append(len(ev)), mark(ev, *a))[-1])
    prev = np.full((2, 3), 100)
    target = np.array([[150, 100, 100], [100, 100, 255]])  # (1, 2) saturated: never scored
    s = PredictionScore()
    s.on_aps_frame(aps(prev, 0, 100))
    for k in range(5):  # nothing sent: the next APS frame is held, not scored
        s.on_events(events_at([(1, 1)], 200 + k))
    assert s.on_aps_frame(aps(prev, 1000, 1100)) == [] and marked == []
    s.on_events(events_at([(0, 0), (1, 2)], 1200))  # before the frame sent
    s.on_emitted(rec(np.array([[150, 90, 90], [100, 100, 200]]), 1500, 1050))
    s.on_aps_frame(aps(target, 2000, 2100))
    (r,) = s.finish()
    assert marked == [2] and r.valid_px == 5 and r.active_px == 1  # (1, 1)'s events came before the held frame
    assert r.psnr_pred_active_db == PSNR_CAP_DB


def test_events_held_unmarked_stay_within_a_few_megabytes_while_nothing_is_sent():
    """APS frames stop while events flow and no frame is sent: the reads kept for marking are bounded by their
    events (256 reads of 64k events each were ~270 MB), and what they mark is the same."""
    from edi_live import quality

    s = PredictionScore()
    s.on_aps_frame(aps(np.full((2, 3), 100), 0, 100))
    big = np.repeat(events_at([(0, 0)], 200), 1 << 16)
    for _ in range(40):
        s.on_events(big)
        assert sum(len(e) for e in s._unmarked) <= quality._UNMARKED_MAX
    s.on_events(events_at([(1, 2)], 300))
    s.on_emitted(rec(np.full((2, 3), 100), 400, 50))
    s.on_events(events_at([(1, 0)], 500))  # a frame was sent: marked as they come, with what was held
    assert s._events_map.reshape(2, 3).tolist() == [[True, False, False], [True, False, True]]


def test_order_of_frame_and_own_deblurred_frame_does_not_matter():
    def run(aps_first):
        s = PredictionScore()
        s.on_aps_frame(aps(np.full((2, 2), 10), 0, 100))
        s.on_emitted(rec(np.full((2, 2), 30), 500, 50))
        s.on_emitted(rec(np.full((2, 2), 40), 1050, 50))
        k1 = aps([[30, 40], [40, 40]], 1000, 1100)
        own = rec(np.full((2, 2), 35), 1050, 1050, "deblurred")
        out = s.on_aps_frame(k1) + s.on_emitted(own) if aps_first else s.on_emitted(own) + s.on_aps_frame(k1)
        return out

    first, late = run(True), run(False)
    assert len(first) == len(late) == 1
    assert first[0] == late[0]
    assert first[0].psnr_pred_db == pytest.approx(psnr_by_hand(np.full((2, 2), (30 * 50 + 40 * 50) / 100), [[30, 40], [40, 40]]))


def dense_reference(frames, start, end, mid):
    """Independent oracle: sample the held honest frame at every µs of [start, end)."""
    honest = sorted((t, i) for i, (t, ref, _) in enumerate(frames) if ref < mid)
    times = np.array([t for t, _ in honest])
    samples = []
    for tau in range(start, end):
        j = np.searchsorted(times, tau, side="right") - 1
        if j < 0:
            return None
        samples.append(frames[honest[j][1]][2].astype(np.float64))
    return np.mean(samples, axis=0)


def test_long_random_stream_matches_a_dense_integration(rng):
    """Many APS frames, frames at random times (some inside the readout gap, some from the next reference),
    so pruning runs many times: every scored prediction equals the 1-µs sampled average of the held frames."""
    s = PredictionScore(window=5)
    frames, windows = [], []
    ref = None
    t = 0
    for k in range(30):
        start = t + int(rng.integers(50, 150))
        end = start + int(rng.integers(1, 200))
        while True:  # latent frames up to the exposure end
            t += int(rng.integers(1, 60))
            if t > end or ref is None:
                break
            image = rng.integers(0, 256, (3, 2))
            frames.append((t, ref, image))
            s.on_emitted(rec(image, t, ref))
        t = end
        b = rng.integers(1, 255, (3, 2))
        mid = (start + end) // 2
        windows.append((start, end, mid, b))
        got = s.on_aps_frame(aps(b, start, end, seq=k))
        ref = mid
        own = rng.integers(0, 256, (3, 2))
        frames.append((mid, mid, own))
        got += s.on_emitted(rec(own, mid, mid, "deblurred"))
        for r in got:
            w_start, w_end, w_mid, w_b = windows[r.seq]
            expected = dense_reference(frames, w_start, w_end, w_mid)
            assert r.scored == (expected is not None)
            if expected is not None:
                np.testing.assert_allclose(s.last_prediction, expected, rtol=0, atol=3e-5)  # float32: ~2 ulp at 255
                assert r.psnr_pred_db == pytest.approx(psnr_by_hand(expected, w_b))
    assert s.scored_total >= 25 and s.frames_dropped == 0
    assert len(s._t) < 40  # pruned: not every frame of the stream is held


def _all_finite_or_none(values):
    return all(v is None or isinstance(v, bool) or math.isfinite(v) for v in values)


def test_no_nan_or_inf_in_degenerate_cases():
    s = PredictionScore()
    assert _all_finite_or_none(s.stats().values()) and s.stats()["pred_psnr_db"] is None
    # empty window: the only frame sent so far comes after it (so the window is complete when it is taken)
    s.on_aps_frame(aps(np.full((2, 2), 80), 0, 100))
    s.on_emitted(rec(np.full((2, 2), 90), 1150, 50))
    (r,) = s.on_aps_frame(aps(np.full((2, 2), 90), 1000, 1100))
    assert r.seq == 0 and not r.scored and r.coverage == 0.0 and r.n_frames_used == 0
    s.on_emitted(rec(np.full((2, 2), 90), 1050, 1050, "deblurred"))  # its own frame: does not count
    # all-saturated and all-black targets: no informative pixel
    s.on_emitted(rec(np.full((2, 2), 90), 1200, 1050))
    s.on_aps_frame(aps(np.full((2, 2), 255), 2000, 2100))
    (r,) = s.on_emitted(rec(np.full((2, 2), 90), 2200, 1050))  # a frame after the window completes it
    assert not r.scored and r.valid_px == 0
    s.on_aps_frame(aps(np.zeros((2, 2)), 3000, 3100))
    (r,) = s.on_emitted(rec(np.full((2, 2), 90), 3200, 1050))
    assert not r.scored and r.valid_px == 0
    # a single held frame over a zero-length exposure
    assert s.on_aps_frame(aps(np.full((2, 2), 100), 4000, 4000)) == []
    (r,) = s.finish()
    assert r.scored and r.n_frames_used == 1 and r.psnr_pred_db == pytest.approx(psnr_by_hand([90], [100]))
    # a frame that starts before any frame was sent: partly covered, unscored
    s2 = PredictionScore()
    s2.on_aps_frame(aps(np.full((2, 2), 80), 0, 100))
    s2.on_emitted(rec(np.full((2, 2), 90), 1050, 50))
    s2.on_aps_frame(aps(np.full((2, 2), 90), 1000, 1100))
    (r,) = s2.finish()
    assert not r.scored and r.coverage == pytest.approx(0.5)
    for sc in (s, s2):
        result = sc.last
        assert _all_finite_or_none([result.psnr_pred_db, result.psnr_still_db, result.psnr_pred_active_db,
                                    result.psnr_still_active_db, result.coverage])
        assert _all_finite_or_none(sc.stats().values())
    assert s.stats()["pred_frames_scored"] == 1 and s.stats()["pred_frames_unscored"] == 3
    assert s.stats()["pred_frames_held"] == 0


def test_aps_frames_with_nothing_sent_since_the_previous_one_are_held_not_scored():
    s = PredictionScore(score_every=2)
    s.on_aps_frame(aps(np.full((2, 2), 80), 0, 100))
    s.on_emitted(rec(np.full((2, 2), 80), 150, 50))
    assert s.on_aps_frame(aps(np.full((2, 2), 85), 1000, 1100)) == []  # the 2nd frame taken: scored later
    assert s.on_aps_frame(aps(np.full((2, 2), 90), 2000, 2100))[0].seq == 0  # nothing sent since: held
    assert s.on_aps_frame(aps(np.full((2, 2), 95), 3000, 3100)) == []  # held as well
    s.on_emitted(rec(np.full((2, 2), 97), 3150, 50))
    s.on_aps_frame(aps(np.full((2, 2), 99), 4000, 4100))  # the 3rd frame not held: skipped by score_every=2
    s.on_emitted(rec(np.full((2, 2), 98), 4150, 50))
    s.on_aps_frame(aps(np.full((2, 2), 100), 5000, 5100, seq=5))  # the 4th: scored against the frame before it
    (r,) = s.finish()
    assert r.seq == 5 and r.scored and r.n_frames_used == 1
    assert r.psnr_pred_db == pytest.approx(psnr_by_hand([98], [100]))
    assert r.psnr_still_db == pytest.approx(psnr_by_hand([99], [100]))  # B_k: the APS frame just before
    st = s.stats()
    assert st["pred_frames_held"] == 2 and st["pred_frames_scored"] == 2 and st["pred_frames_unscored"] == 0


def test_nearest_and_fused_modes_switch_the_figure_off():
    for mode in ("nearest", "fused"):
        s = PredictionScore(mode)
        s.on_aps_frame(aps(np.full((2, 2), 80), 0, 100))
        assert s.on_emitted(rec(np.full((2, 2), 80), 150, 50)) == []
        assert s.on_aps_frame(aps(np.full((2, 2), 80), 1000, 1100)) == [] and s.finish() == []
        st = s.stats()
        assert st["pred_enabled"] is False and st["pred_psnr_db"] is None and st["pred_frames_scored"] == 0


def test_time_going_backwards_starts_over():
    s = PredictionScore()
    s.on_aps_frame(aps(np.full((2, 2), 80), 10_000, 10_100, seq=1))
    s.on_emitted(rec(np.full((2, 2), 80), 10_200, 10_050))
    s.on_aps_frame(aps(np.full((2, 2), 80), 11_000, 11_100, seq=2))
    (r,) = s.on_aps_frame(aps(np.full((2, 2), 80), 0, 100, seq=3))  # the old window is scored, then a reset
    assert r.seq == 2 and r.scored
    s.on_emitted(rec(np.full((2, 2), 80), 200, 50))  # an old frame held from 10_200 must not cover 1000..1100
    s.on_aps_frame(aps(np.full((2, 2), 80), 1000, 1100, seq=4))
    (r,) = s.finish()
    assert r.seq == 4 and r.scored and r.n_frames_used == 1


def test_scoring_one_frame_in_n():
    every, _, _ = run_bar_scene(bright=200, n_frames=7)
    third, _, _ = run_bar_scene(bright=200, n_frames=7, score=PredictionScore(score_every=3))
    assert [r.seq for r in third] == [2, 5] and all(r == every[r.seq - 1] for r in third)


def test_frames_of_another_shape_are_ignored_not_fatal():
    from edi_live.datatypes import Frame, Reconstruction
    from edi_live.quality import PredictionScore

    score = PredictionScore("causal")
    aps = np.full((4, 6), 100, np.uint8)
    score.on_aps_frame(Frame(aps, 0, 1000, 0, 1000, 0))
    odd = Reconstruction(np.zeros((2, 2), np.uint8), 500, "deblurred", 500, 0, 1000, 0.2, 0.2, 0)
    assert score.on_emitted(odd) == []
    score.on_aps_frame(Frame(aps, 2000, 3000, 2000, 3000, 1))
    score.finish()
    assert score.stats()["pred_psnr_db"] is None  # nothing of the right shape was sent: unscored, not an error


@pytest.mark.parametrize("gray", [False, True])
def test_a_colour_source_is_scored_in_the_layout_of_its_output(gray):
    """A colour sensor's APS frames are raw mosaics and its output is demosaiced BGR (or grey): the figure compares
    the output against the APS frame as the node shows it, instead of skipping every frame as another shape."""
    from edi_live.colour import demosaic, mosaic_to_gray

    score = PredictionScore("causal", color_filter="RGGB", gray=gray)
    shown = (lambda m: mosaic_to_gray(m, "RGGB")) if gray else (lambda m: demosaic(m, "RGGB"))
    rng = np.random.default_rng(5)
    results, prev = [], None
    for k in range(4):
        raw = rng.integers(20, 230, (8, 10), dtype=np.uint8)
        start = k * PERIOD
        if prev is not None:  # a "nothing moved" prediction: the previous APS frame as shown, held
            results += score.on_emitted(rec(shown(prev), start - 500, (k - 1) * PERIOD + STEP))
            score.on_events(events_at([(1, 2)], start - 400))
        results += score.on_aps_frame(Frame(raw, start, start + 2 * STEP, seq=k, color_filter="RGGB"))
        results += score.on_emitted(rec(shown(raw), start + STEP, start + STEP, kind="deblurred"))
        prev = raw
    results += score.finish()
    assert len(results) == 3 and all(r.scored for r in results)
    for r in results:
        assert r.psnr_pred_db == r.psnr_still_db  # the held previous frame is exactly the baseline
        assert r.active_px == (1 if gray else 3)  # the one pixel with events, in each of its colours


def test_event_pixels_are_marked_by_the_kernel_as_by_the_numpy_reference():
    """The prediction figure's pixels-with-events map: compiled marking equals numpy's, off-sensor events ignored."""
    import edi_live.edi as edi
    from edi_live.datatypes import EVENT_DTYPE

    rng = np.random.default_rng(4)
    ev = np.zeros(500, EVENT_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, 40, 500), rng.integers(0, 30, 500)  # some beyond a 32x24 sensor
    kernel, ref = np.zeros(32 * 24, bool), np.zeros(32 * 24, bool)
    edi.mark_event_pixels(ev, 32, 24, kernel)
    with edi.numpy_reference():
        edi.mark_event_pixels(ev, 32, 24, ref)
    on = (ev["x"] < 32) & (ev["y"] < 24)
    expected = np.zeros(32 * 24, bool)
    expected[ev["y"][on].astype(int) * 32 + ev["x"][on]] = True
    assert np.array_equal(kernel, expected) and np.array_equal(ref, expected)
