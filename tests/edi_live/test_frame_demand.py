"""Latent frames nobody wants are counted, not rendered, and the frames rendered later are exactly those of a worker
that rendered everything (the latent image moved with every event meanwhile)."""

from __future__ import annotations

import itertools

import numpy as np

from edi_live.config import EdiConfig, NodeConfig
from edi_live.datatypes import Packet, Reconstruction
from edi_live.frame_demand import FrameDemand
from edi_live.node import Node
from edi_live.quality import PredictionScore
from edi_live.reconstructor import EdiReconstructor
from edi_live.ring import EventRing
from edi_live.stats import format_summary
from edi_live.worker import EdiWorker
from tests.edi_live.edi_scenes import make_scene


def scene_packets():
    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=4, sigma_c=0.02, seed=3)
    t = scene.events["t"]
    rng = np.random.default_rng(11)
    packets, cut, frames = [], 0, list(scene.frames)
    while cut < t.size:
        nxt = min(t.size, cut + int(rng.integers(200, 3000)))
        due = [f for f in frames if f.exposure_end_us < t[nxt - 1]]
        frames = frames[len(due):]
        packets.append(Packet(events=scene.events[cut:nxt], frames=due, arrival_ns=10**9 + len(packets)))
        cut = nxt
    return scene, packets


def run(scene, packets, frames_wanted=None):
    ring = EventRing(capacity_events=1 << 20, capacity_frames=16, policy="wait")
    out = []
    worker = EdiWorker(ring, EdiReconstructor(scene.width, scene.height), EdiConfig(every=300), [out.append],
                       frames_wanted=frames_wanted)
    for i, p in enumerate(packets):
        assert ring.push(p, timeout_s=5)
    ring.close()
    worker._run()  # on this thread, after every packet is in: the same chunks in both runs
    assert worker.error is None
    return worker, out


def test_frames_nobody_wants_are_counted_and_later_frames_are_unchanged():
    scene, packets = scene_packets()
    full, every_frame = run(scene, packets)
    answers = itertools.cycle([True, False, False])
    partial, some_frames = run(scene, packets, frames_wanted=lambda: next(answers))
    latent = [r for r in every_frame if r.kind == "latent"]
    rendered = [r for r in some_frames if r.kind == "latent"]
    assert len(latent) > 50 and 0 < len(rendered) < len(latent)
    assert partial.demand.not_rendered == len(latent) - len(rendered)
    assert partial.stats()["frames_not_rendered"] == partial.demand.not_rendered
    assert partial.sent["latent"] == len(rendered) and full.demand.not_rendered == 0
    by_time = {r.t_us: r for r in latent}
    for r in rendered:  # every frame rendered is the one the always-rendering worker made at that event
        same = by_time[r.t_us]
        assert (r.ref_t_us, r.arrival_ns) == (same.ref_t_us, same.arrival_ns)
        assert r.n_events >= same.n_events  # it counts the events of the frames not rendered before it too
        np.testing.assert_array_equal(r.image, same.image)
    assert [r.t_us for r in some_frames if r.kind == "deblurred"] == \
           [r.t_us for r in every_frame if r.kind == "deblurred"]  # deblurred frames are always made


def test_the_quality_score_is_reset_while_nothing_is_shown():
    quality = PredictionScore("causal")
    quality.on_emitted(Reconstruction(np.zeros((2, 2), np.uint8), 5, "latent", 0, 0, 0, 0.2, 0.2, 1))
    demand = FrameDemand(lambda: False)
    assert demand.skip(3, quality) and demand.not_rendered == 3
    assert quality._t == []  # the frames held for scoring were forgotten
    assert not demand.skip(0, quality) and demand.not_rendered == 3  # no frame due: nothing asked
    assert not FrameDemand(None).skip(4, quality) and not FrameDemand(lambda: True).skip(4, quality)


def test_a_node_publishing_to_nobody_renders_no_latent_frame_but_one_writing_out_does(real_recordings, tmp_path):
    import drivers

    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    runs = {}
    for name, extra in (("nobody", {}), ("out", {"out": str(tmp_path / "sharp.aedat4")})):
        config = NodeConfig.from_options({"replay": str(path), "speed": 0, "publish": ["tcp://127.0.0.1:*"],
                                          **extra})
        runs[name] = Node(config, drivers.open_source("replay", path=str(path), speed=0)).run()
    nobody, out = runs["nobody"], runs["out"]
    assert nobody["frames_latent"] == 0 and nobody["frames_not_rendered"] == out["frames_latent"] > 100
    assert nobody["frames_sent"] == 0 and nobody["frames_unsubscribed"] == nobody["frames_deblurred"] > 0
    assert out["frames_not_rendered"] == 0 and out["frames_unsubscribed"] == out["frames_out"]


def test_a_node_without_any_sink_renders_no_latent_frame_and_says_so(real_recordings):
    """--no-publish without --out rendered every latent frame for nobody (a copy, a Reconstruction and the quality
    score's work per frame: ~20 % of the node alone's rate on the demo recording)."""
    import drivers

    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    config = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True})
    stats = Node(config, drivers.open_source("replay", path=str(path), speed=0)).run()
    assert stats["frames_latent"] == 0 and stats["frames_not_rendered"] > 100
    assert stats["frames_deblurred"] > 0  # each deblurred frame is still made: it is the reference the latent image moves from
    summary = format_summary(stats, 1.0)
    assert f"{stats['frames_not_rendered']} latent frames not rendered: nothing takes them" in summary
    assert "prediction of the next APS frame" not in summary


def test_a_node_without_any_sink_scores_no_prediction_nobody_saw(real_recordings):
    """With --every larger than some APS intervals' events, a sinkless node left some intervals without a latent
    frame due: their APS frames were scored against the deblurred frames alone (a prediction nobody received,
    nor would the node have shown), and the summary printed that figure right after saying there was none."""
    import drivers

    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    for extra in ({"every": 40_000}, {"max_fps": 100_000}):
        config = NodeConfig.from_options({"replay": str(path), "speed": 0, "no_publish": True, **extra})
        stats = Node(config, drivers.open_source("replay", path=str(path), speed=0)).run()
        assert stats["frames_deblurred"] > 0 and stats["frames_not_rendered"] + stats["frames_latent"] > 0
        assert not stats.get("pred_frames_scored"), stats.get("pred_frames_scored")
        assert "prediction of the next APS frame" not in format_summary(stats, 1.0)


def test_a_node_publishing_to_nobody_scores_no_prediction_nobody_received(real_recordings):
    """With a publisher and no subscriber, the frames still made (the deblurred frames; every latent frame with
    --max-fps, which asks no demand) were scored: the summary printed a prediction line under 'N latent frames
    not rendered (no subscriber)', a figure of frames nobody received."""
    import drivers

    path = real_recordings["emlb_demo-01_davis346.aedat4"]
    for extra in ({"every": 40_000}, {"max_fps": 100_000}):
        config = NodeConfig.from_options({"replay": str(path), "speed": 0, "publish": ["tcp://127.0.0.1:*"],
                                          **extra})
        stats = Node(config, drivers.open_source("replay", path=str(path), speed=0)).run()
        assert stats["frames_deblurred"] > 0 and stats["frames_sent"] == 0
        assert not stats.get("pred_frames_scored"), stats.get("pred_frames_scored")
        assert "prediction of the next APS frame" not in format_summary(stats, 1.0)
