"""`--mode nearest` hold-back: which latent times wait for the next APS frame (edi_live.nearest_mode) and, through
the worker, that every latent frame is rendered from the nearer APS frame from the first interval on."""

from __future__ import annotations

import numpy as np

from edi_live.config import EdiConfig
from edi_live.datatypes import Packet
from edi_live.nearest_mode import NearestHoldBack
from tests.edi_live.test_worker import aps, events_at, run_worker


def test_without_a_known_interval_every_time_after_the_reference_is_held():
    hold = NearestHoldBack()
    assert not hold.should_hold(5_000, None)
    assert hold.should_hold(1_001, 1_000) and not hold.should_hold(1_000, 1_000)
    hold.new_reference(1_000, 21_000)
    assert not hold.should_hold(21_000 + 5_000, 21_000)  # a quarter interval: nearer the current reference
    assert hold.should_hold(21_000 + 10_001, 21_000)
    hold.gap()
    hold.new_reference(21_000, 500_000)  # across the gap: not an interval
    assert hold.interval_us is None and hold.should_hold(500_001, 500_000)


def test_first_interval_frames_use_the_nearer_frame_too():
    ev = events_at(np.arange(0, 100_000, 5))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(5)]  # f = 1000, 21000, ...
    packets, cut = [], 0
    for f in frames:
        end = int(np.searchsorted(ev["t"], f.exposure_end_us, side="right"))
        packets.append(Packet(events=ev[cut:end], frames=[f]))
        cut = end
    packets.append(Packet(events=ev[cut:]))
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=400, mode="nearest"))
    assert not errors
    fs = np.array([f.mid_exposure_us for f in frames])
    latent = [r for r in out if r.kind == "latent" and r.t_us < fs[-1]]
    assert len(latent) > 20
    for r in latent:
        assert r.ref_t_us == fs[np.argmin(np.abs(fs - r.t_us))], (r.t_us, r.ref_t_us)
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:]))
