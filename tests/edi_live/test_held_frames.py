"""Held frames of `--mode fused` (edi_live.held_frames) with a clock offset: events that arrive late by the offset
the node is told give the same latent frames, at the same scene times, as the same events on time."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.config import EdiConfig
from edi_live.datatypes import Packet
from edi_live.reconstructor import EdiReconstructor
from edi_live.ring import EventRing
from edi_live.simulation import SceneConfig, simulate
from edi_live.worker import EdiWorker


def _fused_frames(sim, delay_us: int) -> dict[int, np.ndarray]:
    """Latent frames by scene time of a fused-mode worker fed `sim` with every event `delay_us` late and the
    reconstructor told that offset (fixed c, so nothing but the offset differs between runs)."""
    cfg = sim.config
    ev = sim.events.copy()
    ev["t"] += delay_us
    ring = EventRing(capacity_events=1 << 20, capacity_frames=64, policy="wait")
    rec = EdiReconstructor(cfg.width, cfg.height, c_on=0.2, c_off=0.2, clock_offset_us=delay_us,
                           mask_flicker_pixels=False)
    out, errors = [], []
    worker = EdiWorker(ring, rec, EdiConfig(every=400, mode="fused", deblur_thread=False, quality_every=0,
                                            heartbeat_s=1e6), [out.append], on_error=errors.append)
    worker.start()
    cut = 0
    for f in sim.frames:  # each frame with the events up to its exposure end, as a camera delivers them
        end = int(np.searchsorted(ev["t"], f.exposure_end_us + delay_us, side="right"))
        assert ring.push(Packet(events=ev[cut:end], frames=[f]), timeout_s=30)
        cut = end
    assert ring.push(Packet(events=ev[cut:]), timeout_s=30)
    ring.close()
    assert worker.done.wait(120) and not errors, errors
    return {r.t_us - delay_us: r.image for r in out if r.kind == "latent"}


@pytest.mark.parametrize("delay_us, exposure_us", [(1500, 8000), (3000, 2000)])
def test_late_events_with_their_offset_give_the_frames_of_on_time_events(delay_us, exposure_us):
    sim = simulate(SceneConfig(width=64, height=48, duration_s=0.3, texture="camera", velocity_px_s=(300.0, 80.0),
                               noise_rate_hz=0.5, seed=12, c_on=0.2, c_off=0.2, exposure_us=exposure_us))
    on_time, late = _fused_frames(sim, 0), _fused_frames(sim, delay_us)
    # the every-N cuts fall a few events apart in the two runs; the frames at the same scene time must agree
    common = sorted(set(on_time) & set(late))
    assert len(common) >= 10
    for t in common:
        assert np.array_equal(late[t], on_time[t]), f"latent frame at {t} µs differs"
