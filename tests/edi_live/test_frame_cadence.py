"""When the worker cuts latent frames (edi_live.frame_cadence): every N events or at the first event `every_ms`
after the previous frame. Oracle: the rule walked event by event; the cadence must agree with it however the
stream is cut into reads, through either of its two entry points (whole reads, or the per-frame takes of the
--max-fps path); the worker on a sparse moving scene keeps its frames that close, and the same whatever its reads."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.config import EdiConfig
from edi_live.errors import ConfigError
from edi_live.frame_cadence import FrameCadence
from tests.edi_live.test_worker_chunking import frames_read_in_chunks
from tools.stream_noise import noisy_scene, scene_packets


def walked(t: np.ndarray, every: int, every_us: int, last_t: int | None) -> list[int]:
    """Indices (into t) of the events that end a frame, by the definition, one event at a time."""
    out, since = [], 0
    for i, ti in enumerate(t.tolist()):
        since += 1
        if since >= every or (every_us and last_t is not None and ti >= last_t + every_us):
            out.append(i)
            since, last_t = 0, ti
    return out


def stream(rng, n: int) -> np.ndarray:
    """Bursts and pauses: gaps from 0 to a few ms, so both rules cut."""
    gaps = np.where(rng.random(n) < 0.05, rng.integers(500, 6000, n), rng.integers(0, 40, n))
    return np.cumsum(gaps).astype(np.int64) + 1_000_000


def cut_in_reads(cadence: FrameCadence, t: np.ndarray, splits: np.ndarray) -> list[int]:
    out, since = [], 0
    for lo, hi in zip(splits[:-1], splits[1:]):
        cuts, since = cadence.cuts(t[lo:hi], since)
        out += [lo + c - 1 for c in cuts]  # (a range or a list)
    return out


def cut_by_takes(cadence: FrameCadence, t: np.ndarray, splits: np.ndarray) -> list[int]:
    """The worker's per-frame path: take, then cut when the count is reached or the time rule is due."""
    out, since = [], 0
    for lo, hi in zip(splits[:-1], splits[1:]):
        pos = lo
        while pos < hi:
            take = cadence.take(t[pos:hi], since)
            pos += take
            since += take
            if since >= cadence.every or cadence.due(int(t[pos - 1])):
                out.append(pos - 1)
                since = 0
                cadence.made(int(t[pos - 1]))
    return out


@pytest.mark.parametrize("seed", range(40))
def test_cuts_follow_the_definition_wherever_the_reads_cut_the_stream(seed):
    rng = np.random.default_rng(seed)
    t = stream(rng, int(rng.integers(1, 3000)))
    every, every_us = int(rng.integers(1, 400)), int(rng.choice([0, 1, 700, 2000, 5000]))
    start = None if seed % 4 == 0 else int(t[0]) - int(rng.integers(0, 8000))  # a frame before the stream, or none
    want = walked(t, every, every_us, start)
    inner = np.sort(rng.choice(np.arange(1, t.size), min(t.size - 1, int(rng.integers(0, 30))), replace=False)) \
        if t.size > 1 else np.zeros(0, np.int64)
    splits = np.concatenate(([0], inner, [t.size]))
    for how in (cut_in_reads, cut_by_takes):
        cadence = FrameCadence(every, every_us)
        if start is not None:
            cadence.made(start)
        assert how(cadence, t, splits) == want, how.__name__


def test_without_a_time_rule_the_cuts_are_every_nth_event():
    cadence = FrameCadence(1000, 0)
    cadence.made(0)
    t = np.arange(0, 10**7, 10_000, dtype=np.int64)  # sparse: a time rule would cut every event
    cuts, left = cadence.cuts(t, since=300)
    assert list(cuts) == list(range(700, t.size + 1, 1000)) and left == t.size - cuts[-1]


def test_bad_cadence_settings_are_refused_with_the_option_named():
    with pytest.raises(ConfigError, match="every-ms must be a number of milliseconds"):
        EdiConfig(every_ms=-1)
    with pytest.raises(ConfigError, match="every-ms"):
        EdiConfig(every_ms=float("nan"))
    with pytest.raises(ValueError):
        FrameCadence(0, 10)


@pytest.fixture(scope="module")
def sparse_scene():
    events, frames, onset_us = noisy_scene(1.2, onset_s=0.9)
    return scene_packets(events, frames), onset_us


@pytest.mark.parametrize("mode", ["causal", "nearest"])  # whole reads; frame by frame (held latent times)
def test_a_sparse_moving_scene_gets_a_frame_within_every_ms_while_events_come(sparse_scene, monkeypatch, mode):
    """--every larger than the scene makes in an APS period: the count rule alone leaves the motion with a frame or
    two per APS frame; the time rule keeps the frames within every_ms (plus the gap to the next event), and the
    still part makes none (its events are noise). Identical frames however the worker's reads are cut."""
    packets, onset_us = sparse_scene
    counted = frames_read_in_chunks(packets, 1 << 16, EdiConfig(every=200_000, every_ms=0, quality_every=0,
                                                                heartbeat_s=3600.0, mode=mode), monkeypatch)
    config = EdiConfig(every=200_000, every_ms=2.0, quality_every=0, heartbeat_s=3600.0, mode=mode)
    runs = {n: frames_read_in_chunks(packets, n, config, monkeypatch) for n in (1 << 16, 997, 61)}
    timed = runs[1 << 16]
    latent = sorted(r.t_us for r in timed if r.kind == "latent")
    assert sum(r.kind == "latent" for r in counted) < 10 < len(latent)
    assert all(t >= onset_us for t in latent), "no frame from the still part's noise"
    assert np.max(np.diff(latent)) < 2_000 + 1_000  # every_ms, plus the wait for the next event
    for n, frames in runs.items():
        assert [(r.kind, r.t_us, r.n_events) for r in frames] == [(r.kind, r.t_us, r.n_events) for r in timed], n
        for a, b in zip(frames, timed):
            assert np.array_equal(a.image, b.image), (n, a.kind, a.t_us)


def test_on_a_slow_real_scene_the_time_rule_adds_latent_frames_and_keeps_every_deblurred_one(real_recordings, tmp_path):
    """evlib (cars seen from a roof, ~40k events/s): by count alone a latent frame every ~25 ms. With the time rule
    the worker's `since` (events since the latest frame) stays small, which must not make its APS frames look
    still: each is deblurred and sent as by count alone."""
    import drivers
    from edi_live.config import NodeConfig
    from edi_live.node import Node

    path = real_recordings["evlib_sample_davis346.aedat4"]
    runs = {}
    for every_ms in (0, 2):
        config = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True, "every_ms": every_ms,
                                          "out": str(tmp_path / f"sharp{every_ms}.aedat4")})
        runs[every_ms] = Node(config, drivers.open_source("replay", path=str(path), speed=0)).run()
    counted, timed = runs[0], runs[2]
    assert timed["frames_latent"] > 5 * counted["frames_latent"]
    assert timed["frames_deblurred"] == counted["frames_deblurred"] == counted["aps_frames_in"]
    assert timed["skipped_static"] == 0


def still_burst_still(noise_hz: float, frame_interval_us: int):
    """A still camera (blocks, 240x180) that moves for 20 ms at 300 px/s from 1.3 s and is still again: its three
    simulated parts (each with `is_noise` per event)."""
    from edi_live.simulation import SceneConfig, simulate

    base = dict(width=240, height=180, noise_rate_hz=noise_hz, frame_interval_us=frame_interval_us,
                exposure_us=10_000, ground_truth=False, texture="blocks")
    parts, t0 = [], 1_000_000
    for seconds, speed in ((0.3, 0.0), (0.02, 300.0), (0.3, 0.0)):
        parts.append(simulate(SceneConfig(duration_s=seconds, velocity_px_s=(speed, 0.0), t0_us=t0, **base)))
        t0 += int(seconds * 1e6)
    return parts


def burst_between_aps_frames() -> list:
    """Weak noise, APS frames 200 ms apart, the 20 ms burst between two of them; the next APS frame comes 220 ms
    after the motion, well after the still-scene test's hold, so its exposure holds noise only (fewer events than
    mark a moving scene) and no event since the latest latent frame is active."""
    parts = still_burst_still(0.05, 200_000)
    moved_from, moved_to = 1_300_000, 1_320_000
    frames = [f for p in parts for f in p.frames if not moved_from <= f.exposure_end_us <= moved_to + 100_000]
    return scene_packets(np.concatenate([p.events for p in parts]), frames)


@pytest.mark.parametrize("mode", ["causal", "nearest"])
def test_every_ms_0_keeps_the_still_scene_decisions_of_the_count_rule(monkeypatch, mode):
    """--every-ms 0 must give the frames of the count rule bit for bit, including which APS frames are deblurred and
    sent: those decisions must not count events that only the time rule's bookkeeping sees (StillFrames.streamed,
    switched off here to get the count rule's decisions)."""
    import edi_live.still_frames

    packets = burst_between_aps_frames()
    config = EdiConfig(every=1000, every_ms=0, quality_every=0, heartbeat_s=1.0, mode=mode)
    now = frames_read_in_chunks(packets, 1 << 16, config, monkeypatch)
    monkeypatch.setattr(edi_live.still_frames.StillFrames, "streamed", lambda self, n: None)
    counted = frames_read_in_chunks(packets, 1 << 16, config, monkeypatch)
    assert any(r.kind == "latent" for r in counted), "the burst made latent frames"
    assert [(r.kind, r.t_us, r.n_events) for r in now] == [(r.kind, r.t_us, r.n_events) for r in counted]
    for a, b in zip(now, counted):
        assert np.array_equal(a.image, b.image), (a.kind, a.t_us)


@pytest.mark.parametrize("mode", ["causal", "nearest"])  # whole reads; frame by frame
def test_the_time_rule_makes_no_frames_from_the_noise_after_the_motion_stops(monkeypatch, mode):
    """A 20 ms burst of motion on a noisy still camera (0.5 events/s per pixel): once the motion's last event is
    in, what follows is sensor noise, which by either rule makes no frame (a heartbeat aside, 1 s away here). The
    still-scene test keeps the events of the next hold_us (50 ms) "active" (so that slow motion is not cut off); the
    time rule must not turn that noise into a frame every every_ms. (One frame just after the end may show the
    motion's last events: those after the latest frame.)"""
    parts = still_burst_still(0.5, 50_000)
    moved = parts[1]
    last_motion_us = int(moved.events["t"][~moved.is_noise].max())
    packets = scene_packets(np.concatenate([p.events for p in parts]), [f for p in parts for f in p.frames])
    for every_ms in (0, 2.0):
        config = EdiConfig(every=1000, every_ms=every_ms, quality_every=0, heartbeat_s=1.0, mode=mode)
        sent = frames_read_in_chunks(packets, 1 << 16, config, monkeypatch)
        latent = sorted(r.t_us for r in sent if r.kind == "latent")
        assert any(t <= last_motion_us for t in latent), "the motion made frames"
        # a frame after the motion's end may show its last events (the time rule's one flush), never noise alone
        noise_only = [t for prev, t in zip(latent, latent[1:]) if prev > last_motion_us]
        assert noise_only == [], f"{len(noise_only)} latent frames from noise after the motion stopped ({every_ms})"


def test_a_time_rule_below_a_microsecond_is_one_microsecond_not_off():
    from edi_live.frame_cadence import frame_cadence_us

    assert frame_cadence_us(0) == 0 and frame_cadence_us(0.0001) == 1 and frame_cadence_us(2) == 2000
    assert frame_cadence_us(3_600_000) == 3_600_000_000  # the largest the option takes: far from int64's range
