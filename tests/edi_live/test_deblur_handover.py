"""The deblur thread (edi_live.deblur_handover) against the inline path, with the real reconstructor on a simulated
scene with a flickering lamp: the same stream gives the same deblurred frames and the same final state whether
each APS frame is deblurred inline or on the helper thread while a streaming copy takes the events. The oracle is
the inline run (no helper thread, no copy, no replay). The handover is made deterministic without sleeps: the
helper thread's deblur starts only once the worker has handed every event up to the next APS frame to the copy
(it waits for the worker to go idle), so the copy always takes several pieces that the original must replay."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import edi_live.deblur_handover as deblur_handover
import edi_live.worker as worker_module
from edi_live.config import EdiConfig
from edi_live.datatypes import Packet, Reconstruction
from edi_live.reconstructor import EdiReconstructor
from edi_live.ring import EventRing
from edi_live.simulation import simulate
from edi_live.simulation.camera import preset
from edi_live.worker import EdiWorker

W, H = 120, 90


@pytest.fixture(scope="module")
def flicker_packets() -> list[Packet]:
    """A translating scene with a 100 Hz lamp: 20 APS frames, each period's events in four packets."""
    cfg = preset("translate", effects=("flicker",), width=W, height=H, duration_s=0.4, ground_truth=False,
                 frame_interval_us=20_000, exposure_us=8_000, first_exposure_us=2_000, t0_us=0)
    sim = simulate(cfg)
    t = sim.events["t"]
    packets: list[Packet] = []
    cut = 0
    for frame in sim.frames:
        end = int(np.searchsorted(t, frame.exposure_end_us, side="right"))
        for part in np.array_split(np.arange(cut, end), 4):
            if part.size:
                packets.append(Packet(events=sim.events[part[0]:part[-1] + 1], arrival_ns=10**9 + len(packets)))
        packets.append(Packet(events=sim.events[:0], frames=[frame], arrival_ns=10**9 + len(packets)))
        cut = end
    packets.append(Packet(events=sim.events[cut:], arrival_ns=10**9 + len(packets)))
    return packets


class IdleRing(EventRing):
    """`idle` is set when the worker waits for data (it has read everything it may read now), cleared when it
    takes an APS frame."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.idle = threading.Event()

    def wait(self, since_version: int, timeout_s: float, wake=None) -> bool:
        self.idle.set()
        return super().wait(since_version, timeout_s, wake)

    def pop_frame(self):
        self.idle.clear()
        return super().pop_frame()


def _gated(ring: IdleRing, **knobs) -> EdiReconstructor:
    class Gated(EdiReconstructor):
        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            if ready is not None:  # on the helper thread: the copy takes every event up to the next frame first
                assert ring.idle.wait(30)
            return super().on_frame(frame, events, arrival_ns, ready=ready)

    return Gated(W, H, **knobs)


def _run(packets: list[Packet], threaded: bool, **knobs) -> tuple[list, EdiWorker, EdiReconstructor]:
    ring = IdleRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    for p in packets:
        assert ring.push(p, timeout_s=5)
    ring.close()
    rec, out = _gated(ring, **knobs), []
    worker = EdiWorker(ring, rec, EdiConfig(every=200, deblur_thread=threaded, quality_every=0), [out.append])
    worker.start()
    assert worker.done.wait(120) and worker.error is None, worker.error
    return out, worker, rec


@pytest.mark.parametrize("catch_up", ["helper", "half", "worker"])
@pytest.mark.parametrize("knobs", [{}, {"denoise_us": 2000}], ids=["batched", "denoised"])
def test_the_deblur_thread_gives_the_inline_frames_on_a_flickering_scene(flicker_packets, monkeypatch, knobs,
                                                                         catch_up):
    """Also with the background-activity filter, where the reconstructor renders frame by frame: the replay
    must then repeat each frame's piece (replay_frames falls back to on_events_frames). The logged calls are
    replayed into the original by the helper thread after settle() (its catch-up), by the worker at adopt(), or
    split between the two: the same frames and state each way."""
    replayed: list[int] = []
    left_for_adopt: list[int] = []
    adopt = deblur_handover.PendingDeblur.adopt

    def counting_adopt(self):
        replayed.append(len(self.calls))
        left_for_adopt.append(len(self.calls) - self.replayed)
        return adopt(self)

    monkeypatch.setattr(deblur_handover.PendingDeblur, "adopt", counting_adopt)
    if catch_up == "worker":
        monkeypatch.setattr(deblur_handover, "_CATCH_UP_ROUNDS", 0)
    elif catch_up == "half":
        monkeypatch.setattr(deblur_handover.PendingDeblur, "_catch_up", lambda self: self._replay(len(self.calls) // 2))
    inline, w_inline, rec_inline = _run(flicker_packets, threaded=False, **knobs)
    assert not replayed
    threaded, w_threaded, rec_threaded = _run(flicker_packets, threaded=True, **knobs)
    assert len(replayed) == 19 and min(replayed) >= 2, "each deblur on the helper thread, the copy fed in pieces"
    expect_left = {"helper": [0] * 19, "worker": replayed, "half": [n - n // 2 for n in replayed]}[catch_up]
    assert left_for_adopt == expect_left, "the helper replays every call logged before it settled (the copy is idle)"
    assert w_threaded.rec is rec_threaded, "the original takes over again after each deblur"
    assert rec_inline.flicker_pixels > 20, "the lamp is found: the scene exercises the flicker mask"

    def deblurred(frames):
        return [r for r in frames if r.kind == "deblurred"]

    assert len(deblurred(inline)) == 20
    for a, b in zip(deblurred(inline), deblurred(threaded)):
        assert b.t_us == a.t_us
        np.testing.assert_array_equal(b.image, a.image, err_msg=f"deblurred frame at {a.t_us}")
    assert [(r.t_us, r.n_events, r.c_on, r.c_off, r.black_level) for r in deblurred(threaded)] == \
           [(r.t_us, r.n_events, r.c_on, r.c_off, r.black_level) for r in deblurred(inline)]
    # latent frames come at the same events (the copy's, until each deblur is adopted, from the older reference)
    assert sorted((r.t_us, r.kind, r.n_events) for r in threaded) == \
           sorted((r.t_us, r.kind, r.n_events) for r in inline)
    np.testing.assert_array_equal(rec_threaded.latent_log_image, rec_inline.latent_log_image)
    assert rec_threaded.stats() | {"last_deblur_ms": 0, "last_estimate_ms": 0, "last_settle_ms": 0} == \
           rec_inline.stats() | {"last_deblur_ms": 0, "last_estimate_ms": 0, "last_settle_ms": 0}
    np.testing.assert_array_equal(rec_threaded.noise_rates().on_hz, rec_inline.noise_rates().on_hz)


def _abort_during_settle(packets: list[Packet]) -> tuple[EdiWorker, EdiReconstructor, threading.Event]:
    """Three APS frames; the helper thread's settle() of the third blocks until the worker was aborted."""
    ring = IdleRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    in_settle, release = threading.Event(), threading.Event()
    frames = [i for i, p in enumerate(packets) if p.frames]
    for p in packets[:frames[2] + 3]:
        assert ring.push(p, timeout_s=5)
    ring.close()

    class BlockedSettle(EdiReconstructor):
        def settle(self):
            if self.frames == 3 and self._calib.pending and not self._streamer:
                in_settle.set()
                assert release.wait(30)
            super().settle()

    rec = BlockedSettle(W, H)
    worker = EdiWorker(ring, rec, EdiConfig(every=200, deblur_thread=True, quality_every=0), [])
    worker.start()
    assert in_settle.wait(30) and ring.idle.wait(30)  # the worker now waits for the pending deblur
    worker.abort()
    return worker, rec, release


def test_an_abort_with_a_deblur_pending_hands_back_the_original_for_the_saved_calibration(flicker_packets):
    worker, rec, release = _abort_during_settle(flicker_packets)
    release.set()  # the settle ends after the abort: the worker must wait for it, not leave the copy in place
    assert worker.done.wait(30) and worker.error is None, worker.error
    assert worker.rec is rec, "stats and a saved calibration must read the original, not the streaming copy"
    assert rec.frames == 3 and rec._pixel_noise.updates >= 1
    rates, own = worker.noise_rates(), rec.noise_rates()
    assert rates is not None
    np.testing.assert_array_equal(rates.on_hz, own.on_hz)
    np.testing.assert_array_equal(rates.seconds, own.seconds)
    assert worker.stats()["c_on"] == round(rec.c_on, 4)


def test_an_abort_while_the_deblur_still_runs_saves_no_noise_rates(flicker_packets, monkeypatch):
    monkeypatch.setattr(worker_module, "_ABORT_DEBLUR_WAIT_S", 0.0)
    worker, rec, release = _abort_during_settle(flicker_packets)
    try:
        assert worker.done.wait(30) and worker.error is None, worker.error
        assert worker.rec is not rec
        assert worker.noise_rates() is None, "the copy's view of the original's statistics, mid-update"
    finally:
        release.set()


def test_a_deblur_that_ends_after_the_worker_was_aborted_sends_nothing(flicker_packets, monkeypatch):
    """Aborted while the helper thread still deblurs (longer than the worker waits for it), the worker ends and the
    node closes its sinks: the helper's frame, ready later, must not reach them (a closed file or socket)."""
    monkeypatch.setattr(worker_module, "_ABORT_DEBLUR_WAIT_S", 0.0)
    ring = IdleRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    frames = [i for i, p in enumerate(flicker_packets) if p.frames]
    for p in flicker_packets[:frames[2] + 3]:
        assert ring.push(p, timeout_s=5)
    ring.close()
    in_deblur, release = threading.Event(), threading.Event()

    class SlowDeblur(EdiReconstructor):
        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            if self.frames == 2 and ready is not None:
                in_deblur.set()
                assert release.wait(30)
            return super().on_frame(frame, events, arrival_ns, ready=ready)

    worker: EdiWorker
    late: list[Reconstruction] = []
    worker = EdiWorker(ring, SlowDeblur(W, H), EdiConfig(every=200, deblur_thread=True, quality_every=0),
                       [lambda r: late.append(r) if worker.done.is_set() else None])
    worker.start()
    assert in_deblur.wait(30) and ring.idle.wait(30)
    pending = worker._pending
    worker.abort()
    assert worker.done.wait(30) and worker.error is None, worker.error
    release.set()
    assert pending is not None and pending.done.wait(30)
    assert pending.result is not None, "the deblur did finish"
    assert late == [], "a frame reached the sinks after the worker ended"


def test_one_helper_thread_deblurs_every_frame_and_sends_each_frame_itself(flicker_packets):
    """The helper thread lives as long as the worker (not one per APS frame) and hands each deblurred frame to the
    sinks itself, the moment it is ready; latent frames leave from the worker thread."""
    ring = IdleRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    for p in flicker_packets:
        assert ring.push(p, timeout_s=5)
    ring.close()
    helpers: list[threading.Thread] = []

    class Recorded(EdiReconstructor):
        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            if ready is not None:
                helpers.append(threading.current_thread())
            return super().on_frame(frame, events, arrival_ns, ready=ready)

    senders: dict[str, set] = {"deblurred": set(), "latent": set()}
    worker = EdiWorker(ring, Recorded(W, H), EdiConfig(every=200, deblur_thread=True, quality_every=0),
                       [lambda r: senders[r.kind].add(threading.current_thread().name)])
    worker.start()
    assert worker.done.wait(120) and worker.error is None, worker.error
    assert len(helpers) == 19 and len(set(helpers)) == 1, "one helper thread for all the frames after the first"
    assert senders == {"deblurred": {"edi-worker", "edi-deblur"}, "latent": {"edi-worker"}}
    assert worker.sent["deblurred"] + worker.skipped_static == 20
    helpers[0].join(10)
    assert not helpers[0].is_alive(), "the helper thread ends with the worker"


def test_the_stats_read_while_a_deblur_is_pending_are_the_originals(flicker_packets):
    """The once-a-second stats may fall while the helper thread deblurs: they must still report the original's
    figures, not the streaming copy's (which watches no flicker and runs no calibration: 0 flicker pixels)."""
    ring = IdleRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    for p in flicker_packets:
        assert ring.push(p, timeout_s=5)
    ring.close()
    in_settle, release = threading.Event(), threading.Event()

    class BlockedSettle(EdiReconstructor):
        def settle(self):
            if not self._streamer and self._calib.pending and self.flicker_pixels and not in_settle.is_set():
                in_settle.set()  # the first deblur after the lamp was found: hold it pending
                assert release.wait(30)
            super().settle()

    rec = BlockedSettle(W, H)
    worker = EdiWorker(ring, rec, EdiConfig(every=200, deblur_thread=True, quality_every=0), [])
    worker.start()
    try:
        assert in_settle.wait(30)
        assert worker.rec is not rec  # the copy streams meanwhile
        stats = worker.stats()
        assert rec.flicker_pixels > 0
        assert stats["flicker_pixels"] == rec.flicker_pixels
        assert stats["c_on"] == round(rec.c_on, 4)
    finally:
        release.set()
    assert worker.done.wait(120) and worker.error is None, worker.error


def test_a_deblurred_frame_sent_by_the_helper_thread_is_counted_when_the_send_aborts_the_worker(flicker_packets):
    """A sink fault on the helper thread's frame aborts the worker (as the node does) before the worker saw the
    frame ready. The frame did reach the sinks, so the counts the final stats report must include it."""
    ring = IdleRing(capacity_events=1 << 22, capacity_frames=64, policy="wait")
    for p in flicker_packets:
        assert ring.push(p, timeout_s=5)
    ring.close()
    received: list[str] = []
    workers: list[EdiWorker] = []

    def sink(r) -> None:
        received.append(r.kind)
        if r.kind == "deblurred" and threading.current_thread().name == "edi-deblur":
            workers[0].abort()  # e.g. the publisher failed on this frame

    rec = _gated(ring)  # the helper deblurs once the worker waits: it cannot see the frame ready before the abort
    worker = EdiWorker(ring, rec, EdiConfig(every=200, deblur_thread=True, quality_every=0), [sink])
    workers.append(worker)
    worker.start()
    assert worker.done.wait(60) and worker.error is None, worker.error
    assert received.count("deblurred") == 2  # the first (inline) and the helper thread's
    assert worker.sent["deblurred"] + worker.skipped_static == received.count("deblurred")
    assert worker.rec is rec
