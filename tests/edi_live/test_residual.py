"""The sub-threshold residual estimate between a pixel's events (edi_live.edi.residual) and what it buys the
fused frames.

Oracles: a hand-made ramp whose true residual is known at every time; the simulator's ground truth."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.datatypes import EVENT_DTYPE
from edi_live.edi import fused
from edi_live.edi.residual import ResidualTracker, exposure_residual
from edi_live.simulation import SceneConfig, simulate
from tests.helpers.fused_pairs import fused_at_truth


def _ramp_events(c: float, period_us: int, n: int, on: bool = True) -> np.ndarray:
    """One pixel (1, 0) of a 3x2 sensor whose log intensity moves steadily by c per period: an event each period."""
    ev = np.zeros(n, EVENT_DTYPE)
    ev["t"] = 1_000 + period_us * np.arange(n)
    ev["x"], ev["y"], ev["p"] = 1, 0, on
    return ev


@pytest.mark.parametrize("numpy_ref", [False, True])
@pytest.mark.parametrize("on", [True, False])
def test_on_a_steady_ramp_the_estimate_beats_the_step(numpy_ref, on):
    c, period = 0.2, 1_000
    ev = _ramp_events(c, period, 12, on)
    err_step, err_est = [], []
    with edi.numpy_reference() if numpy_ref else contextlib.nullcontext():
        tracker = ResidualTracker(ev, 3, 2, c, c)
        for t in range(int(ev["t"][2]) + 37, int(ev["t"][9]), 113):
            truth = (1 if on else -1) * c * ((t - 1_000) % period) / period  # past the last crossing level
            r = tracker.at(t).reshape(2, 3)
            assert r[0, 0] == 0 and r[1, 2] == 0  # pixels without events: the step
            err_step.append(abs(truth))
            err_est.append(abs(truth - r[0, 1]))
            assert np.sign(r[0, 1]) == (1 if on else -1)
    assert np.mean(err_est) < 0.5 * np.mean(err_step), (np.mean(err_est), np.mean(err_step))


def test_without_a_next_event_the_level_drifts_on_in_the_last_direction_and_an_old_event_is_forgotten():
    c = 0.2
    ev = _ramp_events(c, 1_000, 3, on=False)
    tracker = ResidualTracker(ev, 3, 2, c, c)
    last = int(ev["t"][-1])
    r = tracker.at(last + 500).reshape(2, 3)[0, 1]
    assert -0.5 * c < r < 0  # an OFF event last: a little below its level
    assert tracker.at(last + 600, (last + 1, last + 600)).reshape(2, 3)[0, 1] == 0  # last event not seen: step


def _scene(**kw):
    cfg = SceneConfig(width=96, height=72, duration_s=0.22, texture="blocks", velocity_px_s=(150.0, 30.0),
                      noise_rate_hz=0.1, seed=3, **kw)
    return simulate(cfg)


def test_kernels_equal_the_numpy_reference_on_a_simulated_scene():
    sim = _scene(c_on=0.2, c_off=0.16)
    cfg = sim.config
    mask = np.zeros((cfg.height, cfg.width), bool)
    mask[10:20, 30:40] = True
    mids = sim.mid_exposure_us
    times = list(range(int(mids[1]) - 7000, int(mids[3]), 1777))
    seen = [(t - 20_000, t + 9_000) for t in times]
    runs = []
    for ref in (False, True):
        with edi.numpy_reference() if ref else contextlib.nullcontext():
            tracker = ResidualTracker(sim.events, cfg.width, cfg.height, 0.2, 0.16, mask)
            held = exposure_residual(tracker, int(mids[0]), int(mids[1])).copy()
            runs.append([held] + [tracker.at(t, s).copy() for t, s in zip(times, seen)])
    for a, b in zip(*runs):
        np.testing.assert_allclose(a, b, atol=1e-5)
    assert np.all(runs[0][-1].reshape(cfg.height, cfg.width)[mask] == 0)  # masked pixels' events are ignored
    assert np.count_nonzero(runs[0][-1]) > 0.1 * runs[0][-1].size


def test_the_residual_makes_fused_frames_closer_to_the_truth():
    """Fused frames between two deblurred frames (true c) against the ground truth, with the residual estimate
    and with the plain step model (the same fused frame without it: edi.fused_log of the two sides), on a
    photograph moving at 150 px/s. (On slow scenes of flat blocks the two are within 0.3 dB: docs/modes.md.)"""
    from edi_live.reconstructor import EdiReconstructor

    cfg = SceneConfig(width=96, height=72, duration_s=0.3, texture="camera", velocity_px_s=(150.0, 30.0),
                      noise_rate_hz=0.1, seed=5, latent_per_interval=6, c_sigma=0.02)
    sim = simulate(cfg)
    rec = EdiReconstructor(cfg.width, cfg.height, c_on=0.2, c_off=0.2, fused_residual=True)
    ev = sim.events
    mse = {"residual": [], "step": []}
    for g, t, r, prev, cur in fused_at_truth(sim, rec):
        inf0 = edi.blurry_to_float(sim.frames[sim.gt_frame[g]].image)[1]
        inf1 = edi.blurry_to_float(sim.frames[sim.gt_frame[g] + 1].image)[1]
        fwd = prev[0] + edi.event_delta(ev, cfg.width, cfg.height, 0.2, 0.2, t0=prev[1] + 1, t1=t)
        bwd = cur[0] - edi.event_delta(ev, cfg.width, cfg.height, 0.2, 0.2, t0=t + 1, t1=cur[1])
        m = edi.event_mass(ev, cfg.width, cfg.height, 0.2, 0.2, t0=prev[1] + 1, t1=t)
        mt = edi.event_mass(ev, cfg.width, cfg.height, 0.2, 0.2, t0=prev[1] + 1, t1=cur[1])
        _, wb = edi.fusion_weights(m, mt, (t - prev[1]) / (cur[1] - prev[1]), inf0, inf1)
        step = edi.to_uint8(edi.fused_log(fwd, bwd, wb))
        gt = np.clip(sim.gt_images[g], 0, 255)
        mse["residual"].append(np.mean((r.image.astype(np.float64) - gt) ** 2))
        mse["step"].append(np.mean((step.astype(np.float64) - gt) ** 2))
    psnr = {k: float(np.mean(10 * np.log10(255.0 ** 2 / np.array(v)))) for k, v in mse.items()}
    assert len(mse["step"]) >= 20
    assert psnr["residual"] > psnr["step"] + 1.0, psnr  # 36.6 against 34.0 dB when written
