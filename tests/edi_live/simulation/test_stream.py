"""The emulator's endless scene (edi_live.simulation.stream): time order, APS timing, determinism."""

from __future__ import annotations

import itertools

import numpy as np

from edi_live.simulation.stream import generated_scene


def _take(n: int, **kw):
    return list(itertools.islice(generated_scene(64, 48, epoch_us=1_000_000, **kw), n))


def test_packets_are_time_ordered_with_frames_after_their_events():
    packets = _take(30)
    ev = np.concatenate([p.events for p in packets])
    assert ev.size > 0 and np.all(np.diff(ev["t"]) >= 0) and ev["t"].min() >= 1_000_000
    for p in packets:
        for f in p.frames:
            assert f.exposure_end_us <= p.watermark_us and f.image.shape == (48, 64) and f.image.std() > 5
        assert len(p.imu) == 10


def test_frames_follow_the_timing_read_before_each_frame():
    timing = {"exposure_us": 8000, "interval_us": 20000}
    gen = generated_scene(64, 48, epoch_us=0, timing=timing)
    frames = []
    for p in gen:
        frames += p.frames
        if len(frames) == 2:
            timing["exposure_us"] = 3000  # an emulator writes its APS register
        if len(frames) >= 6:
            break
    starts = [f.exposure_start_us for f in frames]
    assert np.diff(starts[:3]).tolist() == [20000, 20000]
    assert [f.exposure_us for f in frames[:2]] == [8000, 8000] and frames[-1].exposure_us == 3000


def test_same_seed_and_epoch_give_the_same_stream_and_another_seed_does_not():
    a, b, c = _take(5), _take(5), _take(5, seed=8)
    for p, q in zip(a, b):
        np.testing.assert_array_equal(p.events, q.events)
    assert not np.array_equal(np.concatenate([p.events for p in a]), np.concatenate([p.events for p in c]))
