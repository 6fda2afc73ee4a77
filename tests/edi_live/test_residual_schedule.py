"""The residual estimate as a schedule of changes (edi_live.edi.residual_schedule) and the fused frames rendered
from it in one kernel call (edi_live.edi.fused): against the numpy reference, which evaluates the estimate at
every pixel at every frame (edi_live.edi.residual.ResidualTracker), with and without the carry between pairs."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.edi as edi
from edi_live.edi.residual_schedule import ResidualCarry
from edi_live.simulation import SceneConfig, simulate


def _pairs(sim, mask=None):
    """(current, previous, informative, times, events window from 4 intervals before f0) per consecutive pair."""
    cfg = sim.config
    rec_logs = []
    for f in sim.frames:
        b, inf = edi.blurry_to_float(f.image)
        rec_logs.append((np.log(np.maximum(b, 1.0)).astype(np.float32), inf, int(f.mid_exposure_us),
                         int(f.exposure_end_us)))
    ev = sim.events
    out = []
    for k in range(1, len(rec_logs)):
        (l0, inf0, f0, _), (l1, inf1, f1, end1) = rec_logs[k - 1], rec_logs[k]
        times = list(range(f0 - 500, f1 + 900, 1_013))  # a few outside the pair, passed through
        win = edi.window(ev, f0 - 4 * (f1 - f0), end1)
        out.append(((l1, f1), (l0, f0), (inf0, inf1), times, win))
    return cfg, out


@pytest.mark.parametrize("masked", [False, True])
def test_scheduled_frames_equal_the_per_frame_reference_and_the_carry_changes_nothing(masked):
    # exposures shorter than the held residual's span: the later window sees events near f0 the earlier did not
    sim = simulate(SceneConfig(width=64, height=48, duration_s=0.3, texture="camera", velocity_px_s=(200.0, 50.0),
                               noise_rate_hz=0.5, seed=11, c_on=0.2, c_off=0.16, exposure_us=8_000))
    mask = None
    if masked:
        mask = np.zeros((48, 64), bool)
        mask[5:12, 20:31] = True
    cfg, pairs = _pairs(sim, mask)
    assert len(pairs) >= 4, len(pairs)
    c = (0.2, 0.16)
    carry = ResidualCarry()
    warm_pairs = 0
    for current, previous, informative, times, events in pairs:
        f0 = previous[1]
        with edi.numpy_reference():
            ref = edi.fused_frames(current, previous, informative, times, events, c, mask)
        cold = edi.fused_frames(current, previous, informative, times, events, c, mask)
        span = int(edi.RESIDUAL_SPAN * (current[1] - f0))
        warm_pairs += carry.warm(f0, span, mask)
        short = edi.window(events, carry.snap_us + 1, None) if carry.warm(f0, span, mask) else events
        warm = edi.fused_frames(current, previous, informative, times, short, c, mask, carry=carry)
        assert [t for _, t, _ in cold] == times and [n for *_, n in cold] == [n for *_, n in ref]
        for (a, *_), (b, *_), (r, *_) in zip(cold, warm, ref):
            np.testing.assert_array_equal(a, b)  # the carry from the last pair: the same frames
            # the reference renders with exp and float64 x: at most 1 DN at the odd rounding boundary
            assert np.abs(a.astype(int) - r.astype(int)).max() <= 1
            assert np.count_nonzero(a != r) <= 0.001 * a.size + 1
    assert warm_pairs == len(pairs) - 1


def test_the_carry_is_cold_after_a_change_of_frame_or_mask_or_a_longer_interval():
    carry = ResidualCarry()
    assert not carry.warm(1000, 300, None)
    carry.f_us, carry.snap_us, carry.mask = 1000, 600, None
    assert carry.warm(1000, 300, None)
    assert not carry.warm(1001, 300, None)
    assert not carry.warm(1000, 400, None)  # the held residual of f0 would need events before the snapshot
    assert not carry.warm(1000, 300, np.zeros((2, 2), bool))
    carry.mask = np.zeros((2, 2), bool)
    assert carry.warm(1000, 300, np.zeros((2, 2), bool))
    assert not carry.warm(1000, 300, np.eye(2, dtype=bool))
    carry.clear()
    assert not carry.warm(1000, 300, carry.mask)


def _worker_frames(sim, monkeypatch, carry: bool) -> dict[int, np.ndarray]:
    """The latent frames of the node's worker in fused mode with the residual estimate, c estimated (its events
    in packets that end at each APS frame's exposure end)."""
    from edi_live.config import EdiConfig
    from edi_live.datatypes import Packet
    from edi_live.edi import residual_schedule
    from edi_live.reconstructor import EdiReconstructor
    from edi_live.ring import EventRing
    from edi_live.worker import EdiWorker

    with monkeypatch.context() as m:
        if not carry:
            m.setattr(residual_schedule.ResidualCarry, "warm", lambda self, *a: False)
        cfg = sim.config
        ring = EventRing(capacity_events=1 << 20, capacity_frames=64, policy="wait")
        rec = EdiReconstructor(cfg.width, cfg.height, fused_residual=True, mask_flicker_pixels=False, joint_pairs=6)
        out, errors = [], []
        worker = EdiWorker(ring, rec, EdiConfig(every=400, mode="fused", deblur_thread=False, quality_every=0,
                                                heartbeat_s=1e6), [out.append], on_error=errors.append)
        worker.start()
        ev, cut = sim.events, 0
        for f in sim.frames:
            end = int(np.searchsorted(ev["t"], f.exposure_end_us, side="right"))
            assert ring.push(Packet(events=ev[cut:end], frames=[f]), timeout_s=30)
            cut = end
        assert ring.push(Packet(events=ev[cut:]), timeout_s=30)
        ring.close()
        assert worker.done.wait(120)
        assert not errors, errors
    return {r.t_us: r.image for r in out if r.kind == "latent"}


def test_the_worker_renders_the_same_frames_with_the_carry_and_the_shorter_windows(monkeypatch):
    """The reconstructor's carry lets the worker pass only the events after its snapshot; against the same run
    with every pair started from four intervals of context (no carry), on a scene with short exposures."""
    sim = simulate(SceneConfig(width=64, height=48, duration_s=0.35, texture="camera", velocity_px_s=(200.0, 50.0),
                               noise_rate_hz=0.5, seed=12, c_on=0.2, c_off=0.2, exposure_us=8_000))
    with_carry = _worker_frames(sim, monkeypatch, carry=True)
    without = _worker_frames(sim, monkeypatch, carry=False)
    assert len(with_carry) > 20 and with_carry.keys() == without.keys()
    for t in with_carry:
        np.testing.assert_array_equal(with_carry[t], without[t])
