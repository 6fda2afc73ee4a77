"""The event clock offset from two APS frames (edi_live.contrast.clock_offset) and the policy that runs it in the
reconstructor (edi_live.clock_offset_policy), on scenes built here with the simulator: with the step model's lag
taken out first (midlevel_times), a 1.5 ms offset is found within 0.3 ms and an ideal camera gives ~0; in a stream
the offset is in use from the fourth frame, and the fit never runs inside on_frame."""

from __future__ import annotations

import collections

import dataclasses

import numpy as np
import pytest

from edi_live.contrast.clock_offset import FrameWindow, estimate_clock_offset, midlevel_times
from edi_live.datatypes import EVENT_DTYPE
from edi_live.simulation import preset, simulate, with_effects


def _median_offset(cfg, pairs: int = 6, *, midlevel: bool = True) -> float:
    sim = simulate(cfg)
    h, w = cfg.height, cfg.width
    sample = np.zeros(h * w, bool)
    sample[np.random.default_rng(0).choice(h * w, 4000, replace=False)] = True
    ev = midlevel_times(sim.events, w) if midlevel else sim.events
    frames = [FrameWindow(f.exposure_start_us, f.exposure_end_us, f.image.astype(np.float64),
                          (f.image > 0) & (f.image < 255)) for f in sim.frames]
    found = []
    for a, b in list(zip(frames[1:-1], frames[2:]))[:pairs]:
        t = ev["t"]
        sub = ev[(t >= a.exposure_start_us - 5000) & (t <= b.exposure_end_us + 5000)]
        d = estimate_clock_offset(sub, a, b, sample.reshape(h, w), (cfg.c_on, cfg.c_off))
        if d is not None:
            found.append(d)
    assert len(found) >= pairs // 2
    return float(np.median(found))


@pytest.fixture(scope="module")
def scene():
    return preset("translate", texture="camera", velocity_px_s=(200.0, 50.0), duration_s=0.45, seed=21,
                  ground_truth=False)


def test_a_late_event_clock_is_found_within_0_3_ms(scene):
    cfg = with_effects(scene, "clock_offset")  # events 1.5 ms late
    assert abs(_median_offset(cfg) - cfg.event_offset_us) <= 300


def test_an_ideal_camera_gives_no_offset_once_the_step_lag_is_out(scene):
    assert abs(_median_offset(scene)) <= 300
    # without the mid-level times the fit absorbs the step model's lag (why it is taken out)
    assert _median_offset(scene, pairs=3, midlevel=False) > 1000


def test_midlevel_times_move_each_event_half_way_back_to_its_predecessor():
    ev = np.zeros(4, EVENT_DTYPE)
    ev["t"] = [100, 200, 400, 50_000]
    ev["x"] = [1, 2, 1, 1]
    ev["p"] = [1, 1, 1, 1]
    out = midlevel_times(ev, width=4, max_gap_us=10_000)
    # pixel 1: its first event has no predecessor, so half the gap to its successor (300 µs) stands in; the last
    # one's gap is capped; pixel 2's event is alone, so it moves by the cap's half
    assert out["t"].tolist() == [200 - 5_000, 100 - 150, 400 - 150, 50_000 - 5_000]
    assert out["x"].tolist() == [2, 1, 1, 1]


def _stream(sim, rec):
    """Feed as the worker does: each exposure's events in the event clock (moved by the offset in use)."""
    ev, frames = sim.events, sim.frames
    t = ev["t"]

    def between(t0, t1):
        return ev[np.searchsorted(t, t0, "left"):np.searchsorted(t, t1, "right")]
    for k, f in enumerate(frames):
        off = rec.clock_offset_us
        rec.on_frame(f, between(f.exposure_start_us + off, f.exposure_end_us + off))
        if k + 1 < len(frames):
            rec.on_events(between(f.exposure_end_us + off + 1, frames[k + 1].exposure_end_us + rec.clock_offset_us))
    return rec


def test_the_reconstructor_finds_the_offset_when_asked_and_keeps_a_given_one(scene):
    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(dataclasses.replace(scene, duration_s=1.2), "clock_offset")
    sim = simulate(cfg)
    rec = _stream(sim, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None))
    physical = rec.stats()["clock_offset_physical_us"]
    assert abs(physical - cfg.event_offset_us) <= 300, rec._clock.last_estimates
    # in use: the camera's offset plus half of EDI's step lag, which is positive and about a millisecond here
    assert physical + 300 <= rec.clock_offset_us <= physical + 3000
    assert rec.stats()["clock_offset_estimated"]
    given = _stream(sim, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=700))
    assert given.clock_offset_us == 700 and not given.stats()["clock_offset_estimated"]


def test_a_still_scene_with_only_noise_events_gives_no_offset():
    """Noise events carry no timing: the cost only drifts across the search range (to +8 ms on this scene, which
    delayed every deblurred frame by 8 ms), and a best point at the range's edge is not a minimum."""
    from edi_live.reconstructor import EdiReconstructor
    from edi_live.simulation import SceneConfig

    cfg = SceneConfig(width=240, height=180, noise_rate_hz=0.5, frame_interval_us=50_000, exposure_us=10_000,
                      ground_truth=False, texture="blocks", duration_s=2.0, velocity_px_s=(0.0, 0.0))
    rec = _stream(simulate(cfg), EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None))
    assert rec.clock_offset_us == 0 and rec._clock.estimates == 0, rec._clock.last_estimates
    assert rec.events_ignored  # the c policy's still verdict ...
    assert rec._clock.fits_run <= 1, rec._clock.fits_run  # ... spares the pairs after it their fits
    assert len(rec._black._pool) <= 1, len(rec._black._pool)  # ... and the black level's pool (12 pairs otherwise)


def test_a_starting_offset_is_used_at_once_and_moved_by_the_stream(scene):
    """A saved calibration's offset is a starting value: in use from the first window, then estimated like any."""
    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(dataclasses.replace(scene, duration_s=1.2), "clock_offset")
    sim = simulate(cfg)
    rec = EdiReconstructor(cfg.width, cfg.height, clock_offset_start_us=5000)
    assert rec.clock_offset_us == 5000 and rec.stats()["clock_offset_from_calibration"]
    _stream(sim, rec)
    assert abs(rec.stats()["clock_offset_physical_us"] - cfg.event_offset_us) <= 300, rec._clock.last_estimates
    assert rec.stats()["clock_offset_estimated"] and not rec.stats()["clock_offset_from_calibration"]


def test_a_starting_offset_beyond_the_search_range_is_kept(scene):
    """A saved offset beyond +-MAX_OFFSET_US (once given with --clock-offset-us and saved) cannot be confirmed by
    the fit, which searches that range: on a camera that has it, the fit's edge value must not replace it."""
    from edi_live.clock_offset_policy import MAX_OFFSET_US
    from edi_live.reconstructor import EdiReconstructor

    cfg = dataclasses.replace(scene, duration_s=1.2, event_offset_us=MAX_OFFSET_US + 4000)
    rec = _stream(simulate(cfg), EdiReconstructor(cfg.width, cfg.height, clock_offset_start_us=cfg.event_offset_us))
    assert rec.clock_offset_us == cfg.event_offset_us, rec._clock.last_estimates
    assert not rec.stats()["clock_offset_estimated"]


def test_the_fits_residual_is_edis_level_tables_and_counts_between_the_frames(scene):
    """The fit reads each pixel's integral of exp(S) at the window ends; EDI's own functions (level tables of both
    windows moved by d, the counts between the mid-exposures) must give the same residual."""
    import edi_live.edi as edi
    from edi_live.contrast.clock_offset import _ExposureSums, _PixelEvents, _terms

    cfg = dataclasses.replace(with_effects(scene, "thresholds"), duration_s=0.15)
    sim = simulate(cfg)
    h, w = cfg.height, cfg.width
    prev, cur = sim.frames[0], sim.frames[1]
    c = (0.21, 0.17)
    pixels = np.sort(np.random.default_rng(3).choice(h * w, 500, replace=False))
    keep = np.zeros(h * w, bool)
    keep[pixels] = True
    ev = edi.events_at_pixels(sim.events, w, h, keep.reshape(h, w))
    dlog_b = np.random.default_rng(4).normal(0.0, 0.3, pixels.size)
    lo, hi = prev.exposure_start_us - 2000, cur.exposure_end_us + 2000
    sums = _ExposureSums(_PixelEvents(ev, pixels, w, None), lo, hi, c)
    ends = np.array([prev.exposure_start_us, prev.exposure_end_us, cur.exposure_start_us, cur.exposure_end_us])
    spans = (prev.exposure_end_us - prev.exposure_start_us, cur.exposure_end_us - cur.exposure_start_us)
    ds = np.array([-2000, -250, 0, 1500, 2000])
    ours = _terms(sums, ends, spans, ds, dlog_b, 0.1)
    inside = ev[(ev["t"] >= lo) & (ev["t"] <= hi)]
    for d, row in zip(ds, ours):
        pred = np.zeros(pixels.size)
        for frame, sign in ((prev, -1.0), (cur, 1.0)):
            table = edi.build_level_table(inside, w, h, frame.exposure_start_us + d, frame.exposure_end_us + d,
                                          segments=True)
            pred[np.searchsorted(pixels, table.pixels)] += sign * edi.log_divisor(table, *c)
        n_on, n_off = edi.signed_counts(inside, w, h, t0=prev.mid_exposure_us + d + 1, t1=cur.mid_exposure_us + d)
        pred += c[0] * n_on[pixels] - c[1] * n_off[pixels]
        np.testing.assert_allclose(row, np.sqrt(0.01 + (dlog_b - pred) ** 2), rtol=1e-6)


def _feed(sim, rec, pieces: int = 1, inside=None):
    """Feed as the worker does: every event through on_events (in `pieces` calls per frame interval) up to the
    exposure's end in the event clock, then the frame with its window's events; returns the offset in use at each
    frame and the deblurred images. `inside(flag)` is told when on_frame starts and ends."""
    ev, frames = sim.events, sim.frames
    t = ev["t"]
    used, images, fed = [], [], 0
    for f in frames:
        while True:  # as the worker's gate: read on until past the exposure's end with the offset now in use
            off = rec.clock_offset_us
            end = max(fed, int(np.searchsorted(t, f.exposure_end_us + off, "right")))
            for part in np.array_split(ev[fed:end], pieces):
                rec.on_events(part)
            fed = end
            if rec.clock_offset_us == off:
                break
        used.append(off)
        if inside:
            inside(True)
        images.append(rec.on_frame(f, ev[np.searchsorted(t, f.exposure_start_us + off, "left"):end]).image)
        if inside:
            inside(False)
        rec.settle()  # the worker's order: the frame's calibration work after the frame was sent
    return used, images


def test_a_stream_uses_the_found_offset_from_the_fifth_frame_and_an_ideal_camera_stays_near_zero(scene):
    from edi_live.reconstructor import EdiReconstructor

    late = with_effects(scene, "clock_offset")
    rec = EdiReconstructor(late.width, late.height, clock_offset_us=None)
    used, _ = _feed(simulate(late), rec)
    # frames 0-1 and 1-2 are the two fits that must agree, each run in the settle() one frame after the pair closed
    assert used[:4] == [0, 0, 0, 0]
    assert all(u == rec.clock_offset_us > 0 for u in used[4:]), used
    assert abs(rec.stats()["clock_offset_physical_us"] - late.event_offset_us) <= 300
    ideal = EdiReconstructor(scene.width, scene.height, clock_offset_us=None)
    _feed(simulate(scene), ideal)
    assert abs(ideal.stats()["clock_offset_physical_us"]) <= 300
    assert ideal.clock_offset_us < late.event_offset_us  # what it keeps of the step lag only


def test_the_fit_runs_in_settle_never_among_latent_frames_and_does_not_depend_on_the_event_batches(scene,
                                                                                                   monkeypatch):
    """settle() runs after the deblurred frame was sent (on the deblur thread when there is one); on_events runs
    between latent frames, which a fit of several ms would hold up."""
    import edi_live.clock_offset_policy as policy
    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(scene, "clock_offset")
    sim = simulate(cfg)
    state = {"where": None, "fits": collections.Counter()}
    real = policy.clock_offset_fit

    def counted(*args, **kwargs):
        fit = real(*args, **kwargs)

        def run(share: float) -> float | None:
            state["fits"][state["where"]] += 1
            return fit(share)
        return run
    monkeypatch.setattr(policy, "clock_offset_fit", counted)
    rec = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None)
    for name in ("on_frame", "on_events", "settle"):
        method = getattr(rec, name)

        def traced(*args, _method=method, _name=name, **kwargs):
            outer, state["where"] = state["where"], state["where"] or _name
            try:
                return _method(*args, **kwargs)
            finally:
                state["where"] = outer
        setattr(rec, name, traced)
    used, images = _feed(sim, rec, 1)
    assert state["fits"]["settle"] >= 2 and state["fits"]["on_events"] == 0 and state["fits"]["on_frame"] == 0
    used7, images7 = _feed(sim, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None), 7)
    assert used7 == used
    assert all(np.array_equal(a, b) for a, b in zip(images, images7))


def test_a_streaming_copy_keeps_the_offset_and_runs_no_fit(scene):
    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(scene, "clock_offset")
    sim = simulate(cfg)
    rec = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None)
    t = sim.events["t"]
    f0, f1 = sim.frames[0], sim.frames[1]
    rec.on_frame(f0, sim.events[np.searchsorted(t, f0.exposure_start_us):np.searchsorted(t, f0.exposure_end_us)])
    rec.settle()
    end1 = np.searchsorted(t, f1.exposure_end_us)
    rec.on_frame(f1, sim.events[np.searchsorted(t, f1.exposure_start_us):end1])
    rec.settle()  # the pair 0-1 is due; its events do not reach the search margin yet
    assert rec._clock.due == 1 and rec._clock.fits_run == 0
    reach = np.searchsorted(t, f1.exposure_end_us + 40_000)
    twin = rec.streaming_copy()
    twin.on_events(sim.events[end1:reach])  # the copy streams; the original gets these events later
    twin.settle()
    assert rec._clock.due == 1 and rec._clock.fits_run == 0 and twin.clock_offset_us == 0
    rec.on_events(sim.events[end1:reach])
    assert rec._clock.fits_run == 0, "no fit among latent frames"
    f2 = sim.frames[2]
    rec.on_frame(f2, sim.events[np.searchsorted(t, f2.exposure_start_us):reach])
    rec.settle()
    assert rec._clock.fits_run == 1 and rec._clock.due == 1  # the pair 0-1 fitted, 1-2 waits


def test_a_new_recording_with_earlier_times_during_the_first_round_still_gets_its_offset(scene):
    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(scene, "clock_offset")
    rec = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None)
    before = dataclasses.replace(scene, duration_s=0.12, seed=5, t0_us=scene.t0_us + 10_000_000)
    _feed(simulate(before), rec)  # two frames of another recording, 10 s later than the next one
    used, _ = _feed(simulate(cfg), rec)
    assert all(u == rec.clock_offset_us > 0 for u in used[4:]), used
    assert abs(rec.stats()["clock_offset_physical_us"] - cfg.event_offset_us) <= 300


def test_a_new_offset_drops_the_pairs_before_it_and_the_frame_that_took_it_opens_the_next(scene):
    """The pairs formed with the old windows go; the frame taken with the new offset pairs with the next one, so
    the c and black-level estimates lose one pair, not two."""
    from edi_live.reconstructor import EdiReconstructor

    late = with_effects(scene, "clock_offset")
    rec = EdiReconstructor(late.width, late.height, clock_offset_us=None)
    seen = []
    on_frame = rec.on_frame

    def counting(*args, **kwargs):
        taken_with = rec.clock_offset_us
        out = on_frame(*args, **kwargs)
        rec.settle()  # the worker's order; the frame's pairs are dropped there
        seen.append((taken_with, len(rec._tracker._pairs)))
        return out

    rec.on_frame = counting
    _feed(simulate(late), rec)
    change = next(i for i in range(1, len(seen)) if seen[i][0] != seen[i - 1][0])
    assert seen[change - 1][1] >= 1 and seen[change][1] == 0, seen
    assert seen[change + 1][1] == 1, seen


def test_a_frozen_copy_still_reports_an_estimated_offset_and_keeps_nothing():
    # the worker's stats come from the streaming copy while the helper thread deblurs: an estimated offset must
    # not read as given there (the status line drops "(estimated)" and the camera's part)
    from edi_live.clock_offset_policy import ClockOffsetPolicy

    policy = ClockOffsetPolicy(None, 8, 6)
    twin = policy.frozen()
    assert twin.estimated and twin.value == policy.value
    ev = np.zeros(50, EVENT_DTYPE)
    ev["t"] = np.arange(50)
    ev["x"], ev["y"] = np.arange(50) % 8, np.arange(50) % 6
    twin.collect(ev)
    assert not twin.collecting and twin._chunks == [] and policy._chunks == []
    assert not ClockOffsetPolicy(1500, 8, 6).frozen().estimated


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_lookup_equals_a_search_of_the_whole_table(seed):
    """last_at_or_before searches each pixel's own entries; numpy's searchsorted over the whole sorted table (the
    reference) gives the same index for every pixel and time in its range, including times before its first
    event (its mark) and on an entry's exact time."""
    from edi_live.contrast._kernels_clock_offset import last_at_or_before

    rng = np.random.default_rng(seed)
    n, span = int(rng.integers(1, 40)), 1000
    counts = rng.integers(0, 6, n)
    key = np.concatenate([i * span + np.r_[0, np.sort(rng.choice(np.arange(1, span - 1), c, replace=False))]
                          for i, c in enumerate(counts)]).astype(np.int64)
    first = np.r_[0, np.cumsum(counts + 1)].astype(np.int64)
    lo = 5000
    row_key = np.arange(n, dtype=np.int64) * span - lo
    q = np.r_[lo, lo + rng.integers(0, span - 1, 12), lo + key[key < span][-1]].astype(np.int64)
    want = np.searchsorted(key, row_key[:, None] + q[None, :], "right") - 1
    np.testing.assert_array_equal(last_at_or_before(key, first, row_key, q), want)


def _offset_fit_inputs(scene, seed: int, k: int):
    """A clock-offset scene's events around frames k and k + 1, those frames as windows, and 3000 sample pixels."""
    cfg = with_effects(scene, "clock_offset")
    sim = simulate(cfg)
    h, w = cfg.height, cfg.width
    sample = np.zeros((h, w), bool)
    sample.reshape(-1)[np.random.default_rng(seed).choice(h * w, 3000, replace=False)] = True
    frames = [FrameWindow(f.exposure_start_us, f.exposure_end_us, f.image.astype(np.float64),
                          (f.image > 0) & (f.image < 255)) for f in sim.frames]
    a, b = frames[k], frames[k + 1]
    t = sim.events["t"]
    ev = sim.events[np.searchsorted(t, a.exposure_start_us - 12_000):np.searchsorted(t, b.exposure_end_us + 8_000)]
    return ev, a, b, sample


def test_the_offset_fit_is_the_same_with_and_without_the_kernels(scene):
    import edi_live.edi as edi

    ev, a, b, sample = _offset_fit_inputs(scene, 1, 2)
    kwargs = dict(midlevel_gap_us=10_000, max_pixels=1500, min_z=2.0, lag_share=0.5)
    got = estimate_clock_offset(ev, a, b, sample, (0.2, 0.2), **kwargs)
    with edi.numpy_reference():
        want = estimate_clock_offset(ev, a, b, sample, (0.2, 0.2), **kwargs)
    assert got is not None and got == want


def test_one_preparation_serves_every_lag_share_as_separate_fits_do(scene):
    """clock_offset_fit takes the pixels and event shifts once; each share's result is estimate_clock_offset's."""
    from edi_live.contrast.clock_offset import clock_offset_fit

    ev, a, b, sample = _offset_fit_inputs(scene, 2, 3)
    kwargs = dict(midlevel_gap_us=10_000, max_pixels=1500, min_z=2.0)
    fit = clock_offset_fit(ev, a, b, sample, (0.2, 0.2), **kwargs)
    shares = (1.0, 0.5, 0.0, 1.0)
    got = [fit(share) for share in shares]
    want = [estimate_clock_offset(ev, a, b, sample, (0.2, 0.2), lag_share=share, **kwargs) for share in shares]
    assert got == want and got[0] is not None and got[1] != got[0]


def test_a_stuck_pixel_neither_overflows_nor_costs_the_pair_its_offset(scene):
    # a pixel firing thousands of ON events in one exposure (a stuck or hot pixel not yet masked) overflowed exp(S):
    # RuntimeWarnings on the terminal and a NaN cost, so the whole pair gave no offset
    import warnings

    ev, a, b, sample = _offset_fit_inputs(scene, 1, 2)
    usable = (sample & a.informative & b.informative & (a.blurry > 20) & (a.blurry < 200)
              & (b.blurry > 20) & (b.blurry < 200))
    y, x = np.argwhere(usable)[0]
    stuck = np.zeros(6000, EVENT_DTYPE)
    stuck["t"] = np.linspace(a.exposure_start_us, b.exposure_end_us, stuck.size).astype(np.int64)
    stuck["x"], stuck["y"], stuck["p"] = x, y, 1
    both = np.concatenate([ev, stuck])
    both = both[np.argsort(both["t"], kind="stable")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = estimate_clock_offset(both, a, b, sample, (0.2, 0.2), midlevel_gap_us=10_000)
    without = estimate_clock_offset(ev, a, b, sample, (0.2, 0.2), midlevel_gap_us=10_000)
    truth = with_effects(scene, "clock_offset").event_offset_us  # the simulator's
    # one pair, no significance test: within 0.5 ms of the truth, and one pixel among thousands barely moves it
    assert got is not None and abs(got - truth) <= 500 and abs(got - without) <= 50


def test_still_frames_before_the_motion_leave_the_offset_to_be_found_once_it_moves(scene):
    """Still pairs are not fitted (nothing in them times the events), and they do not use up the round: a camera
    that starts on a still scene finds its offset when the scene moves."""
    from edi_live.reconstructor import EdiReconstructor

    cfg = with_effects(dataclasses.replace(scene, duration_s=1.2), "clock_offset")
    still = simulate(dataclasses.replace(cfg, velocity_px_s=(0.0, 0.0), duration_s=1.0, noise_rate_hz=0.5))
    moving = simulate(cfg)
    shift = still.frames[-1].exposure_end_us + 50_000 - moving.frames[0].exposure_start_us
    events = moving.events.copy()
    events["t"] += shift
    frames = [dataclasses.replace(f, exposure_start_us=f.exposure_start_us + shift,
                                  exposure_end_us=f.exposure_end_us + shift, start_us=None, end_us=None)
              for f in moving.frames]
    joined = dataclasses.replace(still, events=np.concatenate([still.events, events]),
                                 frames=still.frames + frames)
    rec = EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None)
    _stream(dataclasses.replace(still, frames=joined.frames[:len(still.frames)]), rec)
    fits_still = rec._clock.fits_run
    assert rec.events_ignored and rec._clock.estimates == 0
    rec = _stream(joined, EdiReconstructor(cfg.width, cfg.height, clock_offset_us=None))
    assert abs(rec.stats()["clock_offset_physical_us"] - cfg.event_offset_us) <= 300, rec._clock.last_estimates
    assert fits_still <= 1, fits_still


def _policy_stream(sim, kinds: str):
    """A ClockOffsetPolicy fed as settle() feeds it: per frame `update` ('m', the pair it closes moves) or `still`
    ('s'), and the events up to the next exposure's end collected in between."""
    from edi_live.clock_offset_policy import ClockOffsetPolicy

    h, w = sim.frames[0].image.shape
    policy, ev = ClockOffsetPolicy(None, w, h), sim.events
    t = ev["t"]

    def between(t0, t1):
        return ev[np.searchsorted(t, t0, "left"):np.searchsorted(t, t1, "right")]
    for k, kind in enumerate(kinds):
        f = sim.frames[k]
        if kind == "m":
            policy.update(f, between(f.exposure_start_us, f.exposure_end_us), f.image, 0.0, (0.2, 0.2), None)
        else:
            policy.still(between(f.exposure_start_us, f.exposure_end_us))
        if k + 1 < len(sim.frames):
            policy.collect(between(f.exposure_end_us + 1, sim.frames[k + 1].exposure_end_us))
    return policy


def test_a_moving_pair_waiting_for_its_fit_is_fitted_when_the_scene_turns_still(scene):
    """The still verdict is on the newest pair only: the moving pair before it, whose events are all kept by then,
    is fitted as the next moving frame would have fitted it (a motion of three frames between still ones gave
    one fit, not two)."""
    sim = simulate(with_effects(scene, "clock_offset"))
    moving, turning = _policy_stream(sim, "mmmm"), _policy_stream(sim, "mmms")
    assert moving.fits_run == 2  # (the pair of frames 1 and 2 is fitted at frame 3)
    assert turning.fits_run == moving.fits_run and turning.estimates == moving.estimates
    assert turning._found == moving._found
    # the still frame closes no pair, and nothing is kept until a frame moves
    assert turning.due == 0 and not turning._chunks
