"""The worker's output depends on the event stream only, not on how its reads cut it (a --speed 0 replay gives the
same frames on every run): the same simulated stream (a still camera with sensor noise that starts moving, real
reconstructor) is read in chunks of very different sizes and must give identical frames. The ring is filled and
closed before the worker starts, so each run's chunks are fixed by the chunk size alone (no threads race).
Oracle: the run with the worker's own chunk size; any other cut must match it bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

import edi_live.worker
from edi_live.config import EdiConfig
from edi_live.node import default_reconstructor
from edi_live.ring import EventRing
from edi_live.worker import EdiWorker
from tools.stream_noise import noisy_scene, scene_packets


@pytest.fixture(scope="module")
def scene():
    events, frames, onset_us = noisy_scene(1.3, onset_s=1.0)
    return scene_packets(events, frames), onset_us


def frames_read_in_chunks(packets, chunk_events: int, config: EdiConfig, monkeypatch) -> list:
    monkeypatch.setattr(edi_live.worker, "_CHUNK_EVENTS", chunk_events)
    ring = EventRing(capacity_events=1 << 20, capacity_frames=256, policy="wait")
    for p in packets:
        assert ring.push(p, timeout_s=10)
    ring.close()
    sent: list = []
    worker = EdiWorker(ring, default_reconstructor(240, 180, config), config, [sent.append])
    worker.start()
    assert worker.done.wait(120) and worker.error is None
    return sent


@pytest.mark.parametrize("mode,heartbeat_s", [("causal", 3600.0), ("causal", 0.25), ("nearest", 0.25)])
def test_frames_do_not_depend_on_where_the_reads_cut_the_stream(scene, monkeypatch, mode, heartbeat_s):
    packets, onset_us = scene
    config = EdiConfig(every=1000, heartbeat_s=heartbeat_s, mode=mode, quality_every=0)
    runs = {n: frames_read_in_chunks(packets, n, config, monkeypatch) for n in (1 << 16, 4093, 211, 37)}
    reference = runs[1 << 16]
    assert any(r.t_us >= onset_us and r.kind == "latent" for r in reference)  # the onset and motion made frames
    if heartbeat_s < 1:  # heartbeats in sensor time on the still second (and its static APS frames deblurred)
        assert sum(r.t_us < onset_us for r in reference) >= 4
    for n, frames in runs.items():
        assert [(r.kind, r.t_us, r.n_events) for r in frames] == [(r.kind, r.t_us, r.n_events) for r in reference], n
        for a, b in zip(frames, reference):
            assert np.array_equal(a.image, b.image), (n, a.kind, a.t_us)
