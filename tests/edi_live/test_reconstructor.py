"""EdiReconstructor: streaming order, c caching, incremental latent frames, hot pixels and edge cases."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from tests.edi_live.edi_scenes import make_scene, psnr

import edi_live.contrast as contrast
import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.errors import ConfigError, NodeError
from edi_live.reconstructor import EdiReconstructor


def stream(scene, rec, chunk=500, on_latent=None, settle=True):
    """Feed a scene as a live worker would: events in chunks as they 'arrive'; each APS frame once every event
    up to its exposure end is in, with every event from its exposure start up to now (overlapping on_events);
    settle() after each frame (the worker's order) unless `settle` is False."""
    ev = scene.events
    t = ev["t"]
    outs = []
    fed = 0
    for frame in scene.frames:
        end = int(np.searchsorted(t, frame.exposure_end_us, side="right"))
        while fed < end:
            nxt = min(fed + chunk, ev.size)
            rec.on_events(ev[fed:nxt])
            fed = nxt
            if on_latent and rec.has_reference:
                on_latent(rec, int(t[fed - 1]), ev[:fed])
        start = int(np.searchsorted(t, frame.exposure_start_us, side="left"))
        outs.append(rec.on_frame(frame, ev[start:fed]))
        if settle:
            rec.settle()
    return outs


@pytest.fixture(scope="module")
def brick():
    return make_scene("brick", c_on=0.25, width=80, height=60, n_frames=4, sigma_c=0.02, seed=3)


def test_deblurs_and_estimates_c_while_streaming(brick):
    rec = EdiReconstructor(brick.width, brick.height)
    outs = stream(brick, rec)
    assert [o.kind for o in outs] == ["deblurred"] * 4
    assert abs(rec.c_on - 0.25) <= 0.03 and rec.c_on == rec.c_off
    assert rec.reestimations >= 1
    for out, frame, gt in zip(outs[1:], brick.frames[1:], brick.sharp_mid[1:]):
        assert out.t_us == out.ref_t_us == frame.mid_exposure_us
        assert (out.exposure_start_us, out.exposure_end_us) == (frame.exposure_start_us, frame.exposure_end_us)
        assert psnr(out.image, gt) > psnr(frame.image, gt) + 2.0  # sharper than the blurry APS frame
    assert rec.stats()["reestimations"] == rec.reestimations


def test_ready_gets_the_deblurred_frame_before_the_latent_state_is_readied(brick):
    """on_frame's `ready` callback receives the very frame on_frame returns, before on_frame applies the events
    after the frame (the latent image still stands at the reference then), and ground-truth sharpness holds."""
    rec = EdiReconstructor(brick.width, brick.height)
    given = []

    def ready(out):  # what the latent state holds at that moment
        given.append((out, rec._latent.log_lat.copy()))

    ev, fed = brick.events, 0
    for k, frame in enumerate(brick.frames):
        start = int(np.searchsorted(ev["t"], frame.exposure_start_us, side="left"))
        end = int(np.searchsorted(ev["t"], frame.exposure_end_us + 3000, side="right"))  # events past te too
        rec.on_events(ev[fed:max(fed, start)])
        out = rec.on_frame(frame, ev[start:end], ready=ready)
        fed = end
        rec.settle()
        assert given[-1][0] is out
        assert psnr(out.image, brick.sharp_mid[k]) > psnr(frame.image, brick.sharp_mid[k]) + 2.0 or k == 0
    # events after te were in the batch: the latent image moved on after `ready`
    assert not np.array_equal(given[-1][1], rec._latent.log_lat)


def test_counts_between_frames_are_exact_despite_overlapping_batches(brick):
    rec = EdiReconstructor(brick.width, brick.height)  # c estimated: the reconstructor forms frame pairs
    stream(brick, rec, chunk=333)
    assert rec.pairs
    for pair in rec.pairs:
        f0, f1 = pair.prev.table.ref_t_us, pair.cur.table.ref_t_us
        n_on, n_off = edi.signed_counts(brick.events, brick.width, brick.height, t0=f0 + 1, t1=f1,
                                        mask=rec.hot_pixel_mask)
        np.testing.assert_array_equal(pair.n_on, n_on)
        np.testing.assert_array_equal(pair.n_off, n_off)


def test_incremental_latent_matches_dense_recompute(brick):
    # per-pixel EDI: with the smoothed divisor the latent image starts at te from the median, which a recompute
    # from the per-pixel reference does not see (test_edi_smoothing covers that start)
    rec = EdiReconstructor(brick.width, brick.height, c_on=0.27, c_off=0.22, divisor_median=False)
    checked = []

    def check(r, t_now, fed):
        inc = r.render()
        dense = r.render_from_reference(t_now, fed)
        assert inc.kind == "latent" and inc.t_us == t_now
        assert np.abs(inc.image.astype(int) - dense.image).max() <= 1
        checked.append(t_now)

    stream(brick, rec, chunk=700, on_latent=check)
    assert len(checked) > 10


def test_latent_frames_between_aps_frames_beat_the_blurry_frame(brick):
    rec = EdiReconstructor(brick.width, brick.height, c=0.25)
    gains = []

    def check(r, t_now, fed):
        gt = brick.render(t_now)
        gains.append(psnr(r.render().image, gt) - psnr(brick.frames[0].image, gt))

    stream(brick, rec, chunk=1500, on_latent=check)
    assert np.median(gains) > 0


def test_render_before_f_uses_events_backwards(brick):
    rec = EdiReconstructor(brick.width, brick.height, c=0.25)
    outs = stream(brick, rec)
    f = outs[-1].t_us
    t = brick.frames[-1].exposure_start_us + 500
    back = rec.render_from_reference(t, brick.events)
    assert back.t_us == t and back.ref_t_us == f
    gt = brick.render(t)
    assert psnr(back.image, gt) > psnr(brick.frames[-1].image, gt)


def test_render_returns_a_copy(brick):
    rec = EdiReconstructor(brick.width, brick.height, c=0.25)
    stream(brick, rec)
    a = rec.render()
    a.image[:] = 0
    assert rec.render().image.any()


def test_events_before_first_frame_and_static_scene():
    rec = EdiReconstructor(16, 12)
    ev = np.zeros(5, EVENT_DTYPE)
    ev["t"] = np.arange(5)
    ev["x"] = 3
    rec.on_events(ev)
    assert not rec.has_reference
    with pytest.raises(NodeError, match="before the first APS frame"):
        rec.render()
    img = np.random.default_rng(0).integers(1, 250, (12, 16)).astype(np.uint8)
    out = rec.on_frame(Frame(img, 1000, 21000), np.zeros(0, EVENT_DTYPE))
    assert rec.has_reference
    np.testing.assert_array_equal(out.image, img)  # no events: L(f) = B
    out2 = rec.on_frame(Frame(img, 41000, 61000, seq=1), np.zeros(0, EVENT_DTYPE))
    np.testing.assert_array_equal(out2.image, img)
    assert rec.reestimations == 0  # a static scene says nothing about c
    np.testing.assert_array_equal(rec.render().image, img)


def test_fixed_c_is_never_estimated(brick):
    rec = EdiReconstructor(brick.width, brick.height, c=0.4, reestimate_every=1)
    stream(brick, rec)
    assert rec.c_on == rec.c_off == 0.4 and rec.reestimations == 0


def test_reestimate_every_k_frames(brick):
    rec = EdiReconstructor(brick.width, brick.height, reestimate_every=1)
    stream(brick, rec)
    assert rec.reestimations == 3  # every frame that has a predecessor


def test_hot_pixel_is_masked():
    scene = make_scene("camera", c_on=0.25, width=64, height=48, n_frames=5, hot_pixels=1, hot_rate_hz=5000, seed=1)
    rec = EdiReconstructor(scene.width, scene.height, c=0.25)
    outs = stream(scene, rec)
    idx = edi.flat_index(scene.events, scene.width)
    q = np.bincount(idx).argmax()  # the hot pixel: the one with the most events
    y, x = divmod(int(q), scene.width)
    assert rec.hot_pixels >= 1 and rec.hot_pixel_mask[y, x]
    # a masked pixel keeps its APS value instead of exploding
    assert abs(int(outs[-1].image[y, x]) - int(scene.frames[-1].image[y, x])) <= 1


def test_bad_configuration_and_frame_size():
    with pytest.raises(ConfigError, match="c must be"):
        EdiReconstructor(10, 10, c=0.0)
    with pytest.raises(ConfigError, match="both c_on and c_off"):
        EdiReconstructor(10, 10, c_on=0.2)
    with pytest.raises(ConfigError, match="unknown c estimator"):
        EdiReconstructor(10, 10, estimator="psychic")
    rec = EdiReconstructor(10, 10, c=0.2)
    with pytest.raises(ConfigError, match="set up for 10x10"):
        rec.on_frame(Frame(np.zeros((5, 5), np.uint8), 0, 10), np.zeros(0, EVENT_DTYPE))


def test_energy_estimator_runs_from_the_first_frame(brick):
    rec = EdiReconstructor(brick.width, brick.height, estimator="energy")
    outs = stream(brick, rec)
    assert rec.reestimations >= 1 and 0.01 <= rec.c_on <= 2.0
    assert all(np.isfinite(o.image).all() for o in outs)


def test_numpy_reference_gives_the_same_frames(brick):
    fast = stream(brick, EdiReconstructor(brick.width, brick.height))
    with edi.numpy_reference():
        slow = stream(brick, EdiReconstructor(brick.width, brick.height))
    for a, b in zip(fast, slow):
        assert a.c_on == pytest.approx(b.c_on, abs=1e-6)
        assert np.abs(a.image.astype(int) - b.image).max() <= 1


def test_noise_on_a_static_scene_does_not_degrade_it():
    scene = make_scene("camera", c_on=0.2, velocity_px_per_ms=(0.0, 0.0), width=64, height=48, n_frames=5,
                       noise_hz=2.0, hot_pixels=2, hot_rate_hz=1000, seed=4)
    settled = scene.frames[2].exposure_end_us  # two frame pairs in: the estimator has seen the scene
    for denoise_us in (0, 10_000):
        rec = EdiReconstructor(scene.width, scene.height, denoise_us=denoise_us)
        latent = []

        def check(r, t, fed):
            if t > settled:
                latent.append(psnr(r.render().image, scene.render(t)))

        outs = stream(scene, rec, chunk=200, on_latent=check)
        assert rec.events_ignored  # the consistency fit says: these events do not explain any change
        blurry = np.mean([psnr(f.image, gt) for f, gt in zip(scene.frames[3:], scene.sharp_mid[3:])])
        deblurred = np.mean([psnr(o.image, gt) for o, gt in zip(outs[3:], scene.sharp_mid[3:])])
        assert deblurred >= blurry - 0.5 and np.mean(latent) >= blurry - 0.5, (denoise_us, blurry, deblurred,
                                                                               np.mean(latent))


def test_denoise_filter_keeps_moving_edges(brick):
    plain = stream(brick, EdiReconstructor(brick.width, brick.height, c=0.25))
    filtered = stream(brick, EdiReconstructor(brick.width, brick.height, c=0.25, denoise_us=10_000))
    for a, b, gt in zip(plain[1:], filtered[1:], brick.sharp_mid[1:]):
        assert psnr(b.image, gt) >= psnr(a.image, gt) - 0.3


def test_exp_free_rendering_matches_to_uint8(rng):
    # the fused frame finish renders log L(f) through bucket tables instead of exp: the same uint8 as to_uint8
    # at every float32 value, rounding thresholds included. B = 1 everywhere, so log L(f) = -log D exactly.
    v0, scale, bucket_u8, bucket_thr = edi.render_buckets()
    thr = bucket_thr[np.isfinite(bucket_thr)]
    v = np.concatenate([rng.uniform(-31, 31, 20_000), rng.uniform(-1, 6, 50_000), thr,
                        np.nextafter(thr, np.float32(-np.inf)), np.nextafter(thr, np.float32(np.inf))])
    v = v.astype(np.float32)
    n = v.size
    image = np.ones((1, n), np.uint8)
    divisor = (np.arange(n, dtype=np.int64), -v.astype(np.float64), np.zeros(n, np.float32))
    log_ref, deblurred = np.empty((1, n), np.float32), np.empty((1, n), np.uint8)
    log_lat, display = np.empty((1, n), np.float32), np.empty((1, n), np.uint8)
    edi.finish_frame_u8(image, 255.0, divisor, log_ref, deblurred, log_lat, display)
    np.testing.assert_array_equal(log_ref[0], np.clip(v, edi.LOG_MIN, edi.LOG_MAX))
    np.testing.assert_array_equal(deblurred, edi.to_uint8(log_ref))
    np.testing.assert_array_equal(display, edi.to_uint8(log_lat))


def _simulated(c: float, c_after: float | None = None, duration_s: float = 1.5):
    """The simulator's 'demo' recording (240x180, moving and rotating blocks, background noise, hot pixels) with
    threshold c; with c_after, the same recording follows once more with the threshold changed to c_after."""
    import dataclasses

    from tools.simulate import preset, simulate

    cfg = preset("demo", c_on=c, c_off=c, duration_s=duration_s, ground_truth=False)
    sims = [simulate(cfg)]
    if c_after is not None:
        sims.append(simulate(dataclasses.replace(cfg, c_on=c_after, c_off=c_after,
                                                 t0_us=cfg.t0_us + int(duration_s * 1e6))))
    return SimpleNamespace(events=np.concatenate([s.events for s in sims]), width=cfg.width, height=cfg.height,
                           frames=[f for s in sims for f in s.frames], n_first=len(sims[0].frames))


def _c_per_frame(scene):
    rec = EdiReconstructor(scene.width, scene.height)
    return rec, np.array([o.c_on for o in stream(scene, rec, chunk=5000)])


def test_cached_c_holds_while_c_does_not_change():
    scene = _simulated(0.2)
    rec, cs = _c_per_frame(scene)
    # start-up (two estimates), then the fit test keeps c: the old 3-point test re-estimated 7 times in 30 frames
    # and moved c between 0.183 and 0.213
    assert rec.reestimations <= 0.1 * len(scene.frames), rec.reestimations
    settled = cs[3:]
    assert np.all(np.abs(settled - 0.2) <= 0.03), settled
    assert np.ptp(settled) <= 0.01, settled  # c (and so the output brightness) does not jitter


def test_a_real_change_of_c_is_followed():
    scene = _simulated(0.2, 0.35)
    rec, cs = _c_per_frame(scene)
    n1 = scene.n_first
    assert np.all(np.abs(cs[3:n1] - 0.2) <= 0.03), cs[:n1]
    assert abs(cs[-1] - 0.35) <= 0.03, cs[n1:]  # re-estimated after the change, within the c-recovery tolerance
    assert np.ptp(cs[-5:]) <= 0.01, cs[n1:]  # and settled there


def test_an_estimate_on_a_flat_cost_curve_is_no_information(brick, monkeypatch):
    # the estimator finds some c, but the cost hardly changes around it: the cached c stays
    class Flat(contrast.ConsistencyContrast):
        def estimate(self, cur, pairs, c_init):
            return 0.6, 0.6

        def information(self, pairs, c):
            return 0.5

    monkeypatch.setitem(contrast.ESTIMATORS, "flat", Flat)
    rec = EdiReconstructor(brick.width, brick.height, estimator="flat", c_init=0.25)
    stream(brick, rec)
    assert rec.c_on == rec.c_off == 0.25 and not rec.events_ignored
    assert rec.ill_conditioned >= 1 and rec.stats()["ill_conditioned"] == rec.ill_conditioned


def test_streaming_copy_then_replay_equals_inline_processing(brick):
    """The worker's deblur hand-over: while the original deblurs frame k, a streaming copy renders latent frames
    from the previous reference; the events it applied are then replayed into the original. The original must
    end exactly where inline processing ends (same c, pairs and latent image), and the copy must render what the
    original would have rendered from the old reference."""
    ev, t = brick.events, brick.events["t"]
    inline, handed = EdiReconstructor(brick.width, brick.height), EdiReconstructor(brick.width, brick.height)
    fed = 0
    for k, frame in enumerate(brick.frames):
        end = int(np.searchsorted(t, frame.exposure_end_us, side="right"))
        start = int(np.searchsorted(t, frame.exposure_start_us, side="left"))
        for rec in (inline, handed):
            rec.on_events(ev[fed:end])
        fed = end
        nxt = int(np.searchsorted(t, brick.frames[k + 1].exposure_start_us)) if k + 1 < len(brick.frames) else ev.size
        catchup = ev[end:nxt]  # what arrives while frame k is being deblurred
        out_inline = inline.on_frame(frame, ev[start:end])
        inline.on_events(catchup)
        if handed.has_reference:
            twin = handed.streaming_copy()
            twin.on_events(catchup)  # streams from the old reference ...
            out_handed = handed.on_frame(frame, ev[start:end])  # ... while the original deblurs
            assert twin.render().ref_t_us == brick.frames[k - 1].mid_exposure_us
            handed.on_events(catchup)  # the hand-over replays what the copy applied
        else:
            out_handed = handed.on_frame(frame, ev[start:end])
            handed.on_events(catchup)
        fed = nxt
        np.testing.assert_array_equal(out_handed.image, out_inline.image)
        assert (handed.c_on, handed.c_off, handed.reestimations) == (inline.c_on, inline.c_off, inline.reestimations)
        np.testing.assert_array_equal(handed.applied_counts[0], inline.applied_counts[0])
        np.testing.assert_array_equal(handed.render().image, inline.render().image)
    assert inline.reestimations >= 1


@pytest.mark.parametrize("options", [{"c": 0.25}, {"c": 0.25, "denoise_us": 2000}, {}])
def test_streaming_copy_streams_from_the_old_reference_and_leaves_the_original_alone(brick, options):
    rec = EdiReconstructor(brick.width, brick.height, **options)
    stream(brick, rec)
    twin = rec.streaming_copy()
    later = brick.events[-300:]
    log_lat, counts, pairs = rec.latent_log_image, rec.applied_counts, rec.pairs
    twin.on_events(later)
    twin.mark_gap()  # the worker tells the streaming copy; the original gets it later, when it takes over
    np.testing.assert_array_equal(rec.latent_log_image, log_lat, err_msg="the copy changed the original's image")
    assert all(np.array_equal(a, b) for a, b in zip(rec.applied_counts, counts)), "the copy counted into the original"
    assert rec.pairs == pairs, "mark_gap on the copy reached the original"
    assert pairs or "c" in options, "with c estimated the original holds consistency pairs to protect"
    if "denoise_us" not in options:
        expected = log_lat.copy()
        edi.propagate_log(expected, later, rec.c_on, rec.c_off, mask=rec.hot_pixel_mask)
        np.testing.assert_array_equal(twin.latent_log_image, expected)
        np.testing.assert_array_equal(twin.render().image, edi.to_uint8(expected))
    np.testing.assert_array_equal(rec.render().image, edi.to_uint8(log_lat), err_msg="the original's display moved")
    assert not np.array_equal(twin.latent_log_image, rec.latent_log_image)
    with pytest.raises(NodeError, match="streaming_copy"):
        twin.on_frame(brick.frames[-1], later)


@pytest.mark.parametrize("options", [{}, {"c": 0.25}])
def test_frames_of_a_batch_equal_frame_by_frame_rendering(brick, rng, options):
    """on_events_frames (the worker's hot path) must give exactly the frames, stamps and state of
    on_events(piece) + render() per piece: same pixels, t, n_events, arrival; same latent state and counts."""
    batch, single = (EdiReconstructor(brick.width, brick.height, **options) for _ in range(2))
    ev, t = brick.events, brick.events["t"]
    first = brick.frames[0]
    end = int(np.searchsorted(t, first.exposure_end_us, side="right"))
    start = int(np.searchsorted(t, first.exposure_start_us, side="left"))
    for rec in (batch, single):
        rec.on_events(ev[:end])
        rec.on_frame(first, ev[start:end])
    pos = end
    while pos < ev.size:
        chunk = ev[pos:pos + int(rng.integers(1, 3000))]
        pos += chunk.size
        cuts = sorted(set(rng.integers(1, chunk.size + 1, int(rng.integers(0, 5))).tolist()))
        arrivals = [int(a) for a in rng.integers(1, 10**12, len(cuts))]
        got = batch.on_events_frames(chunk, cuts, arrivals)
        want, i0 = [], 0
        for i1, a in zip(cuts, arrivals):
            single.on_events(chunk[i0:i1], a)
            want.append(single.render())
            i0 = i1
        single.on_events(chunk[i0:])
        assert len(got) == len(want) == len(cuts)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g.image, w.image)
            assert (g.t_us, g.n_events, g.arrival_ns, g.kind, g.ref_t_us) == \
                   (w.t_us, w.n_events, w.arrival_ns, w.kind, w.ref_t_us)
    np.testing.assert_array_equal(batch.latent_log_image, single.latent_log_image)
    np.testing.assert_array_equal(batch.applied_counts[0], single.applied_counts[0])
    np.testing.assert_array_equal(batch.applied_counts[1], single.applied_counts[1])
    assert batch.events_applied == single.events_applied
    last, want = batch.render(), single.render()
    assert (last.n_events, last.t_us) == (want.n_events, want.t_us)
