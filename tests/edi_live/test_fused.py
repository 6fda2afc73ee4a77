"""Fused (two-frame) latent images: the weights (edi_live.edi.fused) and the reconstructor's render_fused.

Oracles: the forward and backward EDI images from edi_live.edi's propagation functions; the simulator's ground
truth for the quality check."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import edi_live.edi as edi
from edi_live.edi import fused
from edi_live.edi.residual import ResidualTracker, exposure_residual
from edi_live.reconstructor import EdiReconstructor
from edi_live.simulation import SceneConfig, simulate
from tests.helpers.fused_pairs import fused_at_truth
from tests.helpers.recordings import packets_by_frame

_FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=200, deadline=None)
@given(crossed=hnp.arrays(np.float64, 12, elements=_FLOATS), total=hnp.arrays(np.float64, 12, elements=_FLOATS),
       tau=_FLOATS, inf0=hnp.arrays(bool, 12), inf1=hnp.arrays(bool, 12))
def test_weights_are_finite_and_sum_to_one_for_every_input(crossed, total, tau, inf0, inf1):
    wf, wb = edi.fusion_weights(crossed, total, tau, inf0, inf1)
    assert np.all(np.isfinite(wf)) and np.all(np.isfinite(wb))
    assert np.all((wb >= 0) & (wb <= 1))
    np.testing.assert_allclose(wf + wb, 1.0, atol=1e-6)


def test_weights_no_events_and_saturated_pixels():
    zero = np.zeros(4)
    inf0 = np.array([True, True, False, False])
    inf1 = np.array([True, False, True, False])  # both / only k / only k+1 / neither informative
    _, wb = edi.fusion_weights(zero, zero, 0.6, inf0, inf1)
    assert wb[1] == 0.0 and wb[2] == 1.0  # the clipped side gets no weight
    assert 0.0 < wb[0] < 1.0 and wb[0] == wb[3]  # no events: time alone shares the two looks at one value


def _scene(**kw):
    cfg = SceneConfig(width=96, height=72, duration_s=0.22, texture="blocks", velocity_px_s=(150.0, 30.0),
                      noise_rate_hz=0.1, seed=3, **kw)
    return simulate(cfg)


def _references(sim, c_on, c_off, **settings):
    """Deblurred frames k=1, 2 from the reconstructor (true c given) and the events between them."""
    cfg = sim.config
    rec = EdiReconstructor(cfg.width, cfg.height, c_on=c_on, c_off=c_off, **settings)
    ev = sim.events
    logs = []
    for f in sim.frames[:3]:
        i0, i1 = np.searchsorted(ev["t"], [f.exposure_start_us, f.exposure_end_us + 1])
        rec.on_frame(f, ev[i0:i1])
        logs.append(rec.reference_log())
    return rec, logs


@pytest.mark.parametrize("numpy_ref, residual", [(False, False), (True, False), (False, True), (True, True)])
def test_fused_equals_forward_at_f_k_and_backward_at_f_k1_and_the_weights_between(numpy_ref, residual):
    sim = _scene(c_on=0.2, c_off=0.16)
    cfg = sim.config
    rec, logs = _references(sim, 0.2, 0.16, fused_residual=residual)
    (log1, f1), (log2, f2) = logs[1], logs[2]
    ev = sim.events
    times = [f1, f1 + (f2 - f1) // 3, f1 + (f2 - f1) * 2 // 3, f2 - 1, f2]
    import contextlib
    with edi.numpy_reference() if numpy_ref else contextlib.nullcontext():
        out = rec.render_fused((log1, f1), sim.frames[1].image, sim.frames[2].image, times, ev)
    assert np.array_equal(out[0].image, edi.to_uint8(log1))  # forward at f_k: L_k(f_k) itself
    assert np.array_equal(out[-1].image, edi.to_uint8(log2))  # backward at f_{k+1}
    inf1 = edi.blurry_to_float(sim.frames[1].image)[1]
    inf2 = edi.blurry_to_float(sim.frames[2].image)[1]
    with edi.numpy_reference():  # the residual estimate (its own tests: test_residual.py), numpy reference
        tracker = ResidualTracker(ev, cfg.width, cfg.height, 0.2, 0.16)
        span = int(fused.RESIDUAL_SPAN * (f2 - f1))
        held1 = exposure_residual(tracker, f1 - span, f1 + span).reshape(log1.shape)
        held2 = exposure_residual(tracker, f2 - span, f2 + span).reshape(log1.shape)
        tracker.restart()
        residuals = [tracker.at(t, fused.residual_seen(t, span)).copy().reshape(log1.shape) for t in times[1:-1]]
    if not residual:  # --fused-residual off (the default): plain two-sided EDI
        held1 = held2 = np.zeros_like(log1)
        residuals = [np.zeros_like(log1)] * len(residuals)
    for t, r, res in zip(times[1:-1], out[1:-1], residuals):
        fwd = log1 - held1 + edi.event_delta(ev, cfg.width, cfg.height, 0.2, 0.16, t0=f1 + 1, t1=t)
        bwd = log2 - held2 - edi.event_delta(ev, cfg.width, cfg.height, 0.2, 0.16, t0=t + 1, t1=f2)
        m = edi.event_mass(ev, cfg.width, cfg.height, 0.2, 0.16, t0=f1 + 1, t1=t)
        mt = edi.event_mass(ev, cfg.width, cfg.height, 0.2, 0.16, t0=f1 + 1, t1=f2)
        _, wb = edi.fusion_weights(m, mt, (t - f1) / (f2 - f1), inf1, inf2)
        want = edi.to_uint8(edi.fused_log(fwd, bwd, wb) + res)
        assert np.mean(np.abs(r.image.astype(int) - want)) < 0.05  # float32 rounding at a few pixels
        assert np.max(np.abs(r.image.astype(int) - want)) <= 1


def test_fused_beats_the_best_single_reference_with_threshold_mismatch():
    sim = _scene(c_on=0.2, c_off=0.16, c_sigma=0.04)
    cfg = sim.config
    c_on = c_off = 0.18  # one c for both polarities: the mismatch EDI meets when it cannot tell them apart
    rec = EdiReconstructor(cfg.width, cfg.height, c_on=c_on, c_off=c_off)
    ev = sim.events
    err = {"forward": [], "backward": [], "nearest": [], "fused": []}
    for g, t, r, prev, cur in fused_at_truth(sim, rec):
        fwd = prev[0] + edi.event_delta(ev, cfg.width, cfg.height, c_on, c_off, t0=prev[1] + 1, t1=t)
        bwd = cur[0] - edi.event_delta(ev, cfg.width, cfg.height, c_on, c_off, t0=t + 1, t1=cur[1])
        gt = np.clip(sim.gt_images[g], 0, 255)
        mse = {"forward": edi.to_uint8(fwd), "backward": edi.to_uint8(bwd), "fused": r.image,
               "nearest": edi.to_uint8(fwd if t - prev[1] <= cur[1] - t else bwd)}
        for name, img in mse.items():
            err[name].append(np.mean((img.astype(np.float64) - gt) ** 2))
    psnr = {name: float(np.mean(10 * np.log10(255.0 ** 2 / np.array(v)))) for name, v in err.items()}
    best_single = max(psnr["forward"], psnr["backward"], psnr["nearest"])
    assert psnr["fused"] > best_single + 0.3, psnr


def test_worker_in_fused_mode_renders_every_latent_frame_between_two_frames_in_time_order():
    from edi_live.config import EdiConfig
    from tests.edi_live.test_worker import run_worker

    sim = _scene()
    cfg = sim.config
    ev = sim.events
    packets = packets_by_frame(ev, sim.frames)
    rec = EdiReconstructor(cfg.width, cfg.height, c=0.2)
    worker, _, out, errors = run_worker(packets, EdiConfig(every=300, mode="fused"), rec=rec, timeout_s=60)
    assert not errors
    mids = sim.mid_exposure_us
    latent = [r for r in out if r.kind == "latent" and r.t_us <= mids[-1]]
    assert len(latent) > 10
    for r in latent:  # stamped with the later of its two frames
        assert r.ref_t_us == mids[np.searchsorted(mids, r.t_us)], (r.t_us, r.ref_t_us)
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:]))
    stats = worker.stats()
    assert stats["fused_added_latency_ms_p50"] is not None and stats["nearest_added_latency_ms_p50"] is None


def test_the_kernel_path_renders_what_the_numpy_reference_does():
    """The plan, time term and propagation kernels (one pass, display through the bucket tables) against the numpy
    reference of the same plan: identical up to float32 rounding at a few pixels."""
    sim = _scene(c_on=0.2, c_off=0.16)
    rec, logs = _references(sim, 0.2, 0.16)
    (log1, f1), (log2, f2) = logs[1], logs[2]
    times = list(range(f1 + 1, f2, max(1, (f2 - f1) // 40)))
    fast = rec.render_fused((log1, f1), sim.frames[1].image, sim.frames[2].image, times, sim.events)
    with edi.numpy_reference():
        slow = rec.render_fused((log1, f1), sim.frames[1].image, sim.frames[2].image, times, sim.events)
    diff = np.stack([np.abs(a.image.astype(int) - b.image.astype(int)) for a, b in zip(fast, slow)])
    assert diff.max() <= 1 and np.count_nonzero(diff) <= 1e-4 * diff.size


def test_frames_after_the_last_reference_are_forward_edi_in_one_pass():
    """render_fused without a previous reference (the held frames at the end of a stream) equals
    render_from_reference at each time."""
    sim = _scene(c_on=0.2, c_off=0.16)
    rec, logs = _references(sim, 0.2, 0.16)
    f2 = logs[2][1]
    times = [f2 + 500 * k for k in range(1, 12)]
    out = rec.render_fused(None, None, None, times, sim.events)
    for t, r in zip(times, out):
        want = rec.render_from_reference(t, sim.events).image
        assert r.t_us == t and np.max(np.abs(r.image.astype(int) - want)) <= 1
        assert np.count_nonzero(r.image != want) <= 1e-4 * want.size


def test_fused_frames_that_cannot_be_held_are_forward_edi_from_the_reference(monkeypatch):
    """The fused mode keeps no causal latent image (follow_latent False). With the hold full (no next APS frame
    for a long time), frames are rendered at once from the reference: the causal mode's frames."""
    from edi_live import fused_mode
    from edi_live.config import EdiConfig
    from tests.edi_live.test_worker import run_worker

    monkeypatch.setattr(fused_mode, "_MAX_HELD", 0)
    sim = _scene()
    ev = sim.events
    packets = packets_by_frame(ev, sim.frames)
    frames = {}
    for mode in ("causal", "fused"):
        rec = EdiReconstructor(sim.config.width, sim.config.height, c=0.2)
        _, _, out, errors = run_worker(packets, EdiConfig(every=300, mode=mode, deblur_thread=False), rec=rec,
                                       timeout_s=60)
        assert not errors
        assert rec.follow_latent == (mode == "causal")
        frames[mode] = {r.t_us: r.image for r in out if r.kind == "latent"}
    assert len(frames["fused"]) > 10 and frames["fused"].keys() == frames["causal"].keys()
    for t, image in frames["fused"].items():
        assert np.max(np.abs(image.astype(int) - frames["causal"][t])) <= 1
