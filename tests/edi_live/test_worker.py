"""EdiWorker policy with a stand-in reconstructor that records what it was given.

The stand-in implements the Reconstructor protocol (edi_live.reconstruction); the oracles are the input events and frames
(which events belong to an exposure, how many latent frames N events make, which APS frame is nearer).
The real reconstructor runs end to end in test_node.py.
"""

from __future__ import annotations

import copy
import threading
import time

import numpy as np
import pytest

import edi_live.worker
from edi_live.config import EdiConfig
from edi_live.datatypes import EVENT_DTYPE, Frame, Packet, Reconstruction
from edi_live.reconstruction import Reconstructor
from edi_live.ring import EventRing
from edi_live.worker import EdiWorker
from tests.helpers.polling import wait_until
from tests.helpers.recordings import packets_by_frame


class StandIn:
    """Records calls; images carry nothing, times and kinds are what the worker is judged on."""

    def __init__(self, fail_on_frame: bool = False) -> None:
        self.has_reference = False
        self.c_on = self.c_off = 0.2
        self.reestimations = 0
        self.hot_pixels = 0
        self.unreliable_pixels = 0
        self.black_level = 0.0
        self.clock_offset_us = 0
        self.aps_gamma = 1.0
        self.follow_latent = True
        self.gaps_marked = 0
        self.ref_f = None
        self.t = None
        self.frames_given = []  # (frame, events) passed to on_frame
        self.events_applied = 0
        self.fail_on_frame = fail_on_frame
        self.settled = 0

    def _rec(self, t, kind):
        return Reconstruction(np.zeros((2, 2), np.uint8), int(t), kind, int(self.ref_f), 0, 0, self.c_on,
                              self.c_off, 0)

    def on_frame(self, frame, events, arrival_ns=0, ready=None):
        if self.fail_on_frame:
            raise RuntimeError("boom")
        self.frames_given.append((frame, events.copy()))
        self.has_reference = True
        self.ref_f = frame.mid_exposure_us
        self.t = int(events["t"][-1]) if len(events) else self.ref_f
        return self._rec(self.ref_f, "deblurred")

    def settle(self):
        self.settled += 1

    def noise_rates(self):
        return None

    def on_events(self, events, arrival_ns=0):
        self.events_applied += len(events)
        self.t = int(events["t"][-1])

    def render(self):
        return self._rec(self.t, "latent")

    def render_from_reference(self, t_us, events):
        return self._rec(t_us, "latent")

    def on_events_frames(self, events, cuts, arrivals):
        out, i0 = [], 0
        for i1, arrival in zip(cuts, arrivals):
            self.on_events(events[i0:i1], arrival)
            out.append(self.render())
            i0 = i1
        if i0 < len(events):
            self.on_events(events[i0:])
        return out

    def replay_frames(self, events, cuts, arrivals):
        self.on_events_frames(events, cuts, arrivals)

    def mark_gap(self):
        self.gaps_marked += 1

    def reference_log(self):
        return np.zeros((2, 2), np.float32), self.ref_f

    def fused_events_from(self, f0_us, f1_us):
        return f0_us - 4 * (f1_us - f0_us)

    def render_fused(self, previous, previous_image, current_image, times, events):
        return [self._rec(t, "latent") for t in times]

    def streaming_copy(self):
        return copy.copy(self)

    def stats(self, current=False):
        return {}


def test_the_stand_in_and_the_real_reconstructor_implement_the_protocol():
    from edi_live.reconstructor import EdiReconstructor

    assert isinstance(StandIn(), Reconstructor)
    assert isinstance(EdiReconstructor(4, 3), Reconstructor)
    assert not isinstance(object(), Reconstructor)


def events_at(t_us) -> np.ndarray:
    ev = np.zeros(len(t_us), EVENT_DTYPE)
    ev["t"] = t_us
    ev["x"] = np.arange(len(t_us)) % 7
    return ev


def aps(t0, t1) -> Frame:
    return Frame(np.zeros((2, 2), np.uint8), exposure_start_us=t0, exposure_end_us=t1)


def run_worker(packets, config, rec=None, timeout_s=10.0, close=True):
    ring = EventRing(capacity_events=1 << 14, capacity_frames=8, policy="wait")
    rec = rec or StandIn()
    out, errors = [], []
    worker = EdiWorker(ring, rec, config, [out.append], on_error=errors.append)
    worker.start()
    for p in packets:
        assert ring.push(p, timeout_s=timeout_s)
    if close:
        ring.close()
        assert worker.done.wait(timeout_s), "worker did not finish after close()"
    return worker, rec, out, errors


def test_deblur_gets_every_event_of_the_exposure_and_latent_frames_follow_every_n():
    t = np.arange(0, 20_000, 4)  # 5000 events, one per 4 µs
    ev = events_at(t)
    f = aps(1000, 3000)
    # the frame is delivered in the packet that holds its exposure end, as the Packet contract requires
    packets = [Packet(events=ev[:600]), Packet(events=ev[600:900], frames=[f]), Packet(events=ev[900:])]
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=500, every_ms=0))  # by event count only
    assert not errors
    (frame, given), = rec.frames_given
    inside = ev[(ev["t"] >= 1000) & (ev["t"] <= 3000)]
    assert np.all(np.isin(inside["t"], given["t"])), "every exposure event reaches on_frame"
    assert given["t"].min() >= 1000
    assert [r.kind for r in out][0] == "deblurred"
    after = np.sum(ev["t"] > given["t"].max())  # events streamed after the deblur
    assert rec.events_applied == after
    assert sum(r.kind == "latent" for r in out) == after // 500
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:])), "frames leave in time order"


def test_with_a_clock_offset_the_deblur_waits_for_the_late_events_of_the_exposure():
    # events lag the APS clock by 2 ms: the exposure [1000, 3000] is [3000, 5000] in the event clock, and the
    # frame (queued after its stated end) must wait until an event past 5000 was read
    t = np.arange(0, 20_000, 4)
    ev = events_at(t)
    rec = StandIn()
    rec.clock_offset_us = 2000
    packets = [Packet(events=ev[:600]), Packet(events=ev[600:900], frames=[aps(1000, 3000)]),
               Packet(events=ev[900:1300]), Packet(events=ev[1300:])]
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=500), rec=rec)
    assert not errors
    (frame, given), = rec.frames_given
    assert given["t"].min() >= 3000 and given["t"].max() > 5000, "the window in the event clock is complete"
    assert np.all(np.isin(ev["t"][(ev["t"] >= 3000) & (ev["t"] <= 5000)], given["t"]))


def test_with_a_clock_offset_the_worker_reads_only_through_the_late_window_before_the_deblur():
    # everything arrives at once (a replay at --speed 0): reading on past the first event after te + offset
    # before the deblur would hand the later events to the old reference, and the new one would get no frames
    t = np.arange(0, 20_000, 4)
    ev = events_at(t)
    rec = StandIn()
    rec.clock_offset_us = 2000
    worker, rec, out, errors = run_worker([Packet(events=ev, frames=[aps(1000, 3000)])],
                                          EdiConfig(every=500, every_ms=0), rec=rec)  # by event count only
    assert not errors
    (frame, given), = rec.frames_given
    assert given["t"].max() == t[t > 5000][0], "read through the first event after the late window, no further"
    after = int(np.sum(t > given["t"].max()))
    latent = [r for r in out if r.kind == "latent" and r.ref_t_us == frame.mid_exposure_us]
    assert len(latent) == after // 500, "the events after the window make latent frames from the new frame"


def test_an_aps_frame_pushed_between_the_workers_look_and_its_read_is_deblurred_before_later_events():
    # A replay sends each APS frame after the events up to its exposure end, so it lands at the ring's head: at
    # the worker's cursor once the worker has read them. Pushed just after the worker found no frame queued,
    # with the next packet's events, it must still be deblurred before any of those later events are read, as
    # when it was queued before the look (a replay is repeatable however the threads interleave).
    ev = events_at(np.arange(0, 4000))
    late = aps(1600, 1999)

    class PushDuringLook(EventRing):
        injected = False

        def peek_frame(self):
            entry = super().peek_frame()
            if entry is None and self.read_index == 2000 and not self.injected:
                self.injected = True  # the replay's pump, between this look and the worker's read
                assert self.push(Packet(frames=[late])) and self.push(Packet(events=ev[2000:]))
            return entry

    ring = PushDuringLook(capacity_events=1 << 14, capacity_frames=8, policy="wait")
    rec, errors = StandIn(), []
    worker = EdiWorker(ring, rec, EdiConfig(every=500), [], on_error=errors.append)
    assert ring.push(Packet(events=ev[:2000], frames=[aps(100, 500)]))
    worker.start()
    assert ring.wait_consumer_idle(10.0)
    ring.close()
    assert worker.done.wait(10.0) and not errors and ring.injected
    (_, first), (frame, given) = rec.frames_given
    assert frame is late
    np.testing.assert_array_equal(given["t"], np.arange(1600, 2000))  # its exposure, nothing past its end


def test_with_a_clock_offset_activity_before_a_deblurred_exposure_does_not_count_as_after_it():
    # Events lag the APS clock by 5 ms. Motion in event time [22, 25) ms ends before the second frame's exposure
    # in the event clock ([25, 27] ms), so that deblur saw its result; the third frame, with only sensor noise
    # since, is a still scene and is not deblurred (heartbeat 60 s). Judged against the exposure end in the APS
    # clock (22 ms), the motion looked like activity after the reference and the third frame was deblurred.
    rng = np.random.default_rng(5)
    side = 100
    noise_t = np.sort(rng.integers(0, 70_000, 700))  # 10 events/ms on 10^4 pixels: 1 Hz per pixel
    motion_t = np.arange(22_000, 25_000, 33)  # a row of neighbouring pixels, ~30 events/ms
    t = np.concatenate([noise_t, motion_t])
    x = np.concatenate([rng.integers(0, side, noise_t.size), (motion_t // 33) % side])
    y = np.concatenate([rng.integers(0, side, noise_t.size), 50 + (motion_t // 33) % 2])
    order = np.argsort(t, kind="stable")
    ev = np.zeros(t.size, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"] = t[order], x[order], y[order]

    def frame(t0, t1):
        return Frame(np.zeros((side, side), np.uint8), exposure_start_us=t0, exposure_end_us=t1)

    rec = StandIn()
    rec.clock_offset_us = 5000
    frames = [frame(1000, 2000), frame(20_000, 22_000), frame(50_000, 52_000)]
    worker, rec, out, errors = run_worker([Packet(events=ev, frames=frames)], EdiConfig(every=1000, heartbeat_s=60),
                                          rec=rec)
    assert not errors and worker.frames_in == 3
    exposure = (ev["t"] >= 55_000) & (ev["t"] <= 57_000)
    assert exposure.sum() >= 16  # enough events that only the activity test can call the scene still
    assert [f.exposure_end_us for f, _ in rec.frames_given] == [2000, 22_000]
    assert worker.skipped_static_deblur == 1


def test_no_frames_before_the_first_aps_frame():
    worker, rec, out, errors = run_worker([Packet(events=events_at(np.arange(5000)))], EdiConfig(every=100))
    assert not errors and out == [] and rec.events_applied == 0


class FrozenClock:
    """Stands in for the `time` module inside edi_live.worker: monotonic() (the clock of --max-fps and the
    heartbeat) moves only when the test advances it, so counts do not depend on how fast this machine is.
    Everything else is the real `time`. Values are binary fractions, so sums are exact."""

    def __init__(self, start_s: float = 1024.0) -> None:
        self.now = start_s

    def monotonic(self) -> float:
        return self.now

    def advance(self, seconds: float) -> None:
        self.now += seconds

    def __getattr__(self, name: str):
        return getattr(time, name)


@pytest.fixture
def clock(monkeypatch) -> FrozenClock:
    frozen = FrozenClock()
    monkeypatch.setattr(edi_live.worker, "time", frozen)
    return frozen


class Collect:
    """A sink that lets the test wait (with a timeout) for the n-th frame."""

    def __init__(self) -> None:
        self.frames: list[Reconstruction] = []
        self._cond = threading.Condition()

    def __call__(self, rec: Reconstruction) -> None:
        with self._cond:
            self.frames.append(rec)
            self._cond.notify_all()

    def wait_for(self, n: int, timeout_s: float = 10.0) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.frames) >= n, timeout_s), f"fewer than {n} frames came"


def test_max_fps_caps_latent_frames_and_counts_the_rest(clock):
    ev = events_at(np.arange(0, 100_000, 2))  # 50,000 events; the APS frame [0, 10] takes the first 6
    ring = EventRing(capacity_events=1 << 17, capacity_frames=8, policy="wait")
    out, errors = Collect(), []
    worker = EdiWorker(ring, StandIn(), EdiConfig(every=100, max_fps=0.5, heartbeat_s=64.0), [out],
                       on_error=errors.append)
    worker.start()
    # the deblurred frame goes out, then 5000 events: 50 latent frames due, all within 2 s of it -> all skipped
    ring.push(Packet(events=ev[:5006], frames=[aps(0, 10)]))
    wait_until(lambda: worker.skipped_max_fps == 50)
    clock.advance(2.5)  # past the 2 s cap: the next due frame goes out, the 448 after it are skipped again
    ring.push(Packet(events=ev[5006:]))
    ring.close()
    assert worker.done.wait(10) and not errors
    assert [r.kind for r in out.frames] == ["deblurred", "latent"]
    assert worker.skipped_max_fps == 50 + 448
    assert 1 + worker.skipped_max_fps == (len(ev) - 6) // 100


class WaitRecordingRing(EventRing):
    """Records how long the worker asks to sleep each time it has nothing to do."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.idle_timeouts: list[float] = []

    def wait(self, since_version: int, timeout_s: float, wake=None) -> bool:
        self.idle_timeouts.append(timeout_s)
        return super().wait(since_version, timeout_s, wake)


def test_static_scene_heartbeat_only_and_no_busy_loop(clock):
    heartbeat_s = 0.125
    ring = WaitRecordingRing(capacity_events=1 << 12, policy="wait")
    out = Collect()
    worker = EdiWorker(ring, StandIn(), EdiConfig(every=100, heartbeat_s=heartbeat_s), [out])
    worker.start()
    ring.push(Packet(events=events_at(np.arange(10)), frames=[aps(0, 9)]))
    out.wait_for(1)
    for k in range(1, 6):  # nothing arrives: one heartbeat per heartbeat_s of clock time, nothing else
        clock.advance(heartbeat_s)
        ring.poke()
        out.wait_for(1 + k)
    ring.close()
    assert worker.done.wait(5)
    assert [r.kind for r in out.frames] == ["deblurred"] + ["latent"] * 5 and worker.heartbeats == 5
    # idle, the worker sleeps on the ring until the next heartbeat is due (the clock stands still meanwhile),
    # never in short polling steps
    assert ring.idle_timeouts and all(t == heartbeat_s for t in ring.idle_timeouts), ring.idle_timeouts


def test_static_aps_frames_are_not_sent_again():
    # two APS frames with few events between them (activity on the 2x2 sensor, but too few to show): the second
    # one is not sent. The events span a few ms, as the activity test judges 1 ms spans of the event clock.
    ev = events_at(np.arange(0, 50) * 100)
    packets = [Packet(events=ev[:10], frames=[aps(0, 900)]), Packet(events=ev[10:], frames=[aps(2000, 4900)])]
    # (every_ms=0: 40 events over 4 ms would make latent frames by the time rule, test_frame_cadence.py)
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=1000, heartbeat_s=60, every_ms=0))
    assert len(rec.frames_given) == 2  # both deblurred (the reference follows the newest frame)
    assert [r.kind for r in out] == ["deblurred"]
    assert worker.skipped_static == 1


@pytest.mark.parametrize("mode", ["causal", "nearest", "fused"])
def test_a_source_without_events_passes_every_aps_frame_that_changed_through(mode):
    """A frames-only recording (or a camera whose DVS is off) has no event to tell a still scene from a moving
    one: an APS frame that changed is what is known, and is sent (before, all but the first were taken for a
    still scene)."""
    frames = [Frame(np.full((2, 2), 10 * k, np.uint8), exposure_start_us=k * 50_000,
                    exposure_end_us=k * 50_000 + 5_000) for k in range(6)]
    packets = [Packet(events=np.zeros(0, EVENT_DTYPE), frames=[f]) for f in frames]
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=1000, mode=mode))
    assert not errors
    assert [r.kind for r in out] == ["deblurred"] * 6
    assert [r.t_us for r in out] == [f.mid_exposure_us for f in frames]


def test_a_source_without_events_sends_an_unchanged_aps_frame_only_as_the_heartbeat():
    """A perfect sensor's still scene (no events, the same APS frame 20 times a second) stays at the heartbeat,
    as a still scene with events does; read noise does not count as a change, a changed frame does."""
    rng = np.random.default_rng(3)
    still = np.full((20, 30), 100, np.uint8)
    images = [np.clip(still + rng.integers(-3, 4, still.shape), 0, 255).astype(np.uint8) for _ in range(40)]
    images[30] = images[30].copy()
    images[30][:10] = 200  # something changed in the APS frame, and stays
    images[31:] = [images[30].copy() for _ in range(9)]
    frames = [Frame(img, exposure_start_us=k * 50_000, exposure_end_us=k * 50_000 + 5_000)
              for k, img in enumerate(images)]
    packets = [Packet(events=np.zeros(0, EVENT_DTYPE), frames=[f]) for f in frames]
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=1000, heartbeat_s=1.0))
    assert not errors
    sent = [round((r.t_us - 2_500) / 50_000) for r in out]  # the APS frame each came from
    assert sent == [0, 20, 30], sent  # the first, the heartbeat a second later, the change


def test_gap_suspends_latent_frames_until_the_next_aps_frame():
    ev = events_at(np.arange(0, 30_000, 3))
    packets = [Packet(events=ev[:100], frames=[aps(0, 250)]),
               Packet(events=ev[100:4000]),
               Packet(events=ev[4000:8000], gap=True),
               Packet(events=ev[8000:8100], frames=[aps(24_000, 24_250)]),
               Packet(events=ev[8100:])]
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=500))
    assert worker.gaps == 1
    t_gap, t_frame2 = int(ev["t"][4000]), 24_250
    assert not [r for r in out if r.kind == "latent" and t_gap <= r.t_us < t_frame2]
    assert any(r.kind == "latent" and r.t_us > t_frame2 for r in out)


def test_nearest_mode_references_each_latent_frame_to_the_nearer_aps_frame():
    ev = events_at(np.arange(0, 100_000, 5))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(5)]  # f = 1000, 21000, ...
    packets = packets_by_frame(ev, frames)
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=400, mode="nearest"))
    assert not errors
    fs = np.array([f.mid_exposure_us for f in frames])
    latent = [r for r in out if r.kind == "latent"]
    assert len(latent) > 20
    for r in latent:
        if r.t_us < fs[-1]:  # from the first interval on (before the fix, it only held once two frames were in)
            assert r.ref_t_us == fs[np.argmin(np.abs(fs - r.t_us))], (r.t_us, r.ref_t_us)
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:])), "nearest mode keeps time order"
    assert worker.stats()["nearest_added_latency_ms_p50"] is not None


@pytest.mark.parametrize("mode", ["nearest", "fused"])
def test_held_latent_frames_go_out_before_a_later_frame_when_the_aps_frames_stop(mode):
    """The APS frames stop while events keep coming: the latent times held for the next APS frame go out, from the
    last reference, before the heartbeat that a second without a frame sent brings (it came first, out of order)."""
    ev = events_at(np.arange(0, 1_600_000, 50))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(3)]  # then none for 1.5 s
    worker, rec, out, errors = run_worker(packets_by_frame(ev, frames), EdiConfig(every=400, mode=mode))
    assert not errors
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:])), "frames in time order"
    assert len([r for r in out if r.kind == "latent"]) >= len(ev) // 400 - 5  # none lost
    late = [r for r in out if r.t_us > 200_000]
    assert late and max(r.t_us for r in late) - min(r.t_us for r in late) > 1_000_000, "they kept coming"


@pytest.mark.parametrize("mode", ["nearest", "fused"])
def test_a_heartbeat_inside_the_next_aps_frames_window_keeps_time_order(mode):
    """APS frames stop for ~1 s, then one comes whose exposure holds the heartbeat's sensor time: no frame later
    than that APS frame's deblurred frame goes out before it (the heartbeat did, from the 1 s old reference)."""
    ev = events_at(np.arange(0, 1_200_000, 50))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(3)] + [aps(1_032_000, 1_042_000)]
    worker, rec, out, errors = run_worker(packets_by_frame(ev, frames), EdiConfig(every=400, mode=mode))
    assert not errors
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:])), [(r.t_us, r.kind) for r in out]


def test_no_two_frames_share_a_time_when_the_aps_frames_stop():
    ev = events_at(np.arange(0, 1_200_000, 50))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(3)]
    worker, rec, out, errors = run_worker(packets_by_frame(ev, frames), EdiConfig(every=400, mode="nearest"))
    ts = [r.t_us for r in out]
    assert len(ts) == len(set(ts)), sorted(t for t in set(ts) if ts.count(t) > 1)


@pytest.mark.parametrize("mode", ["nearest", "fused"])
def test_a_heartbeat_shorter_than_the_aps_period_keeps_latent_frames_on_their_nearest_references(mode):
    """--heartbeat-s 0.04 with APS frames every 50 ms (or APS frames slower than 1 s at the default): the latent
    frames between two APS frames are still rendered from the nearer one (nearest), from both (fused)."""
    period = 50_000
    ev = events_at(np.arange(0, 4 * period + 5_000, 50))
    frames = [aps(k * period, k * period + 2_000) for k in range(5)]
    mids = np.array([f.mid_exposure_us for f in frames])
    worker, rec, out, errors = run_worker(packets_by_frame(ev, frames),
                                          EdiConfig(every=100, mode=mode, heartbeat_s=0.04))
    assert not errors
    lat = [r for r in out if r.kind == "latent" and mids[0] < r.t_us < mids[-1]]
    if mode == "nearest":
        want = [int(mids[np.argmin(abs(mids - r.t_us))]) for r in lat]
    else:
        want = [int(mids[np.searchsorted(mids, r.t_us)]) for r in lat]
    wrong = [(r.t_us, r.ref_t_us, w) for r, w in zip(lat, want) if r.ref_t_us != w]
    assert len(wrong) <= 1, f"{len(wrong)} of {len(lat)} from the wrong reference: {wrong[:5]}"


def test_nearest_mode_sends_what_it_holds_before_a_frame_it_can_no_longer_hold(monkeypatch):
    """Past the hold's cap a latent frame goes out at once from the older reference; the held ones go first."""
    from edi_live import nearest_mode

    monkeypatch.setattr(nearest_mode, "_MAX_HELD", 8)
    ev = events_at(np.arange(0, 200_000, 5))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(3)]  # then none for 150 ms: 150 latent times
    worker, rec, out, errors = run_worker(packets_by_frame(ev, frames), EdiConfig(every=400, mode="nearest"))
    assert not errors
    assert all(a.t_us <= b.t_us for a, b in zip(out, out[1:])), "frames in time order"


@pytest.mark.parametrize("mode", ["causal", "nearest", "fused"])
def test_a_still_scene_with_aps_frames_gets_one_heartbeat_per_heartbeat_s(mode):
    """Noise only (0.5 events/s per pixel on 240x180) and APS frames every 50 ms for 6 s, heartbeat 1 s: a frame
    about once a second in every mode (a held time counting as sent must not silence a still scene)."""
    from tests.helpers.recordings import events_at_random_pixels

    rng = np.random.default_rng(1)
    duration = 6_000_000
    ev = events_at_random_pixels(np.sort(rng.integers(0, duration, int(240 * 180 * 0.5 * duration / 1e6))), rng)
    frames = [Frame(np.zeros((180, 240), np.uint8), exposure_start_us=k * 50_000, exposure_end_us=k * 50_000 + 5_000)
              for k in range(duration // 50_000)]
    worker, rec, out, errors = run_worker(packets_by_frame(ev, frames), EdiConfig(every=1000, mode=mode))
    assert not errors
    ts = [r.t_us for r in out]
    assert all(a <= b for a, b in zip(ts, ts[1:]))
    assert 5 <= len(ts) - 1 <= 7 and np.diff(ts).max() < 1_100_000, [(r.t_us, r.kind) for r in out]


@pytest.mark.parametrize("mode", ["causal", "nearest"])
def test_frames_do_not_depend_on_when_the_producer_pushed_a_late_frame(mode):
    """The same packets (a frame after events past its exposure end, as a live DAVIS sends it after the readout),
    pushed in lockstep with the worker or all before it starts: the same frames (a heartbeat that looked at whether
    the frame was queued yet came out in one case only)."""
    ev = events_at(np.arange(0, 1_200_000, 50))
    f0, f1 = aps(0, 2_000), aps(995_000, 1_005_000)
    cut = int(np.searchsorted(ev["t"], 1_007_000))
    packets = [Packet(events=ev[:10], frames=[f0]), Packet(events=ev[10:cut]), Packet(events=ev[:0], frames=[f1]),
               Packet(events=ev[cut:])]
    config = EdiConfig(every=100_000, mode=mode, heartbeat_s=1.0)
    runs = []
    for lockstep in (True, False):
        ring = EventRing(capacity_events=1 << 16, capacity_frames=8, policy="wait")
        out: list = []
        worker = EdiWorker(ring, StandIn(), config, [out.append])
        if lockstep:
            worker.start()
        for p in packets:
            assert ring.push(p, timeout_s=10)
            if lockstep:
                assert ring.wait_consumer_idle(10)
        ring.close()
        if not lockstep:
            worker.start()
        assert worker.done.wait(20)
        runs.append([(r.t_us, r.kind) for r in out])
    assert runs[0] == runs[1]


def test_causal_mode_uses_the_latest_frame():
    ev = events_at(np.arange(0, 60_000, 5))
    frames = [aps(k * 20_000, k * 20_000 + 2_000) for k in range(3)]
    packets = packets_by_frame(ev, frames)
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=400))
    for r in out:
        assert r.ref_t_us <= r.t_us


def test_reconstructor_failure_reaches_on_error_and_ends_the_thread():
    ev = events_at(np.arange(100))
    worker, rec, out, errors = run_worker([Packet(events=ev, frames=[aps(0, 50)])], EdiConfig(),
                                          rec=StandIn(fail_on_frame=True))
    assert len(errors) == 1 and "boom" in str(errors[0])
    assert worker.done.is_set()


def test_abort_stops_without_draining():
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    worker = EdiWorker(ring, StandIn(), EdiConfig(), [])
    worker.start()
    worker.abort()
    assert worker.join(timeout_s=2)


@pytest.mark.parametrize("config", [EdiConfig(every=1, deblur_thread=False),  # the batched causal path
                                    EdiConfig(every=1, max_fps=1e9, deblur_thread=False)])  # frame by frame
def test_abort_stops_within_a_chunk_of_many_frames(config):
    # --every 1: one 64k-event read is 64k latent frames (~40 s of colour frames); abort was looked at only
    # between reads, so a --duration or Ctrl-C run ended in "edi-worker did not stop within their timeout"
    # (exit 1) with the frames made meanwhile counted as sent but never written to --out
    ev = events_at(np.arange(0, 80_000, 4))  # 20000 events, all read at once
    ring = EventRing(capacity_events=1 << 16, capacity_frames=8, policy="wait")
    assert ring.push(Packet(events=ev[:500], frames=[aps(100, 1000)]), timeout_s=5)
    assert ring.push(Packet(events=ev[500:]), timeout_s=5)
    ring.close()
    out: list = []

    def sink(rec: Reconstruction) -> None:
        out.append(rec)
        if len(out) == 40:
            worker.abort()

    worker = EdiWorker(ring, StandIn(), config, [sink])
    worker.start()
    assert worker.join(timeout_s=60) and worker.error is None
    assert 40 <= len(out) <= 40 + edi_live.worker._BATCH_FRAMES, len(out)  # the batch under way, no more


@pytest.mark.parametrize("mode", ["causal", "nearest"])
def test_stats_map_has_the_published_keys(mode):
    worker, rec, out, errors = run_worker([], EdiConfig(mode=mode))
    s = worker.stats()
    for key in ("c", "c_on", "c_off", "reestimations", "frames_latent", "frames_deblurred", "events_processed"):
        assert key in s


def test_frames_without_events_are_not_deblurred_again_on_a_static_scene():
    ev = events_at(np.arange(0, 50))
    packets = [Packet(events=ev, frames=[aps(0, 49)])]
    packets += [Packet(frames=[aps(1000 * k, 1000 * k + 500)]) for k in range(1, 6)]  # no events at all
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=1000, heartbeat_s=60))
    assert len(rec.frames_given) == 1 and worker.skipped_static_deblur == 5
    assert [r.kind for r in out] == ["deblurred"]


class SlowDeblur(StandIn):
    def on_frame(self, frame, events, arrival_ns=0, ready=None):
        if self.has_reference:
            threading.Event().wait(0.05)  # a long deblur: latent frames must not wait for it
        return super().on_frame(frame, events, arrival_ns)


def two_frame_packets():
    ev = events_at(np.arange(0, 60_000, 5))
    frames = [aps(0, 2_000), aps(20_000, 22_000)]
    packets = packets_by_frame(ev, frames, tail=False)
    cut = sum(p.events.size for p in packets)
    # the rest in small packets, so the worker streams while the second frame is being deblurred
    packets += [Packet(events=ev[k:k + 200]) for k in range(cut, len(ev), 200)]
    return ev, frames, packets


def stream_to_the_end(rec, config: EdiConfig, packets, sinks):
    """A worker on `rec` fed every packet through a ring, then closed; returns it once it has finished."""
    ring = EventRing(capacity_events=1 << 16, policy="wait")
    worker = EdiWorker(ring, rec, config, sinks)
    worker.start()
    for p in packets:
        assert ring.push(p, timeout_s=5)
    ring.close()
    assert worker.done.wait(10) and worker.error is None
    return worker


def test_deblur_thread_keeps_latent_frames_flowing_and_hands_every_event_to_the_new_reference():
    ev, frames, packets = two_frame_packets()
    rec, out = SlowDeblur(), []
    worker = stream_to_the_end(rec, EdiConfig(every=400, deblur_thread=True), packets, [out.append])
    assert worker.rec is rec, "the reconstructor itself takes over again after the deblur"
    assert len(rec.frames_given) == 2
    after_first = int(np.sum(ev["t"] > frames[0].exposure_end_us))
    assert rec.events_applied == after_first, "every event reaches the reconstructor exactly once"
    f1, f2 = frames[0].mid_exposure_us, frames[1].mid_exposure_us
    deblurred_at = [i for i, r in enumerate(out) if r.kind == "deblurred" and r.t_us == f2][0]
    meanwhile = [r for r in out[:deblurred_at] if r.kind == "latent" and r.t_us > frames[1].exposure_end_us]
    assert meanwhile and all(r.ref_t_us == f1 for r in meanwhile), "old reference while the new one is made"
    assert all(r.ref_t_us == f2 for r in out[deblurred_at + 1:])


class Uncopyable(StandIn):
    def __init__(self):
        super().__init__()
        self.lock = threading.Lock()  # deepcopy fails on locks


def test_deblur_inline_when_the_reconstructor_cannot_be_copied():
    ev, frames, packets = two_frame_packets()
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=400, deblur_thread=True), rec=Uncopyable())
    assert not errors and len(rec.frames_given) == 2
    assert sum(r.kind == "deblurred" for r in out) == 2


def test_deblur_thread_failure_reaches_on_error():
    class FailSecond(StandIn):
        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            if self.has_reference:
                raise RuntimeError("second frame failed")
            return super().on_frame(frame, events, arrival_ns, ready=ready)

    ev, frames, packets = two_frame_packets()
    worker, rec, out, errors = run_worker(packets, EdiConfig(every=400, deblur_thread=True), rec=FailSecond())
    assert len(errors) == 1 and "second frame failed" in str(errors[0])


def test_batched_latent_frames_equal_the_frame_by_frame_path():
    """Without --max-fps the worker makes a chunk's latent frames in one reconstructor call; with a cap that never
    binds it takes the frame-by-frame path. Both must send the same frames, split at the same events."""
    from tests.edi_live.edi_scenes import make_scene

    from edi_live.reconstructor import EdiReconstructor

    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=4, sigma_c=0.02, seed=3)
    t = scene.events["t"]
    rng = np.random.default_rng(7)
    packets, cut, frames = [], 0, list(scene.frames)
    while cut < t.size:
        nxt = min(t.size, cut + int(rng.integers(50, 2500)))
        due = [f for f in frames if f.exposure_end_us < t[nxt - 1]]
        frames = frames[len(due):]
        # fixed arrival stamps, so that both runs must stamp each frame alike
        packets.append(Packet(events=scene.events[cut:nxt], frames=due, arrival_ns=10**9 + len(packets)))
        cut = nxt
    for every in (300, 7):  # at 7, a 64k-event chunk is split into several reconstructor calls
        sent = {}
        for max_fps in (None, 1e12):
            rec = EdiReconstructor(scene.width, scene.height)
            batches = []
            batch_call = rec.on_events_frames

            def counted(ev, cuts, arrivals, batch_call=batch_call, batches=batches):
                batches.append(len(cuts))
                return batch_call(ev, cuts, arrivals)

            rec.on_events_frames = counted
            ring = EventRing(capacity_events=1 << 20, capacity_frames=16, policy="wait")
            out = []
            worker = EdiWorker(ring, rec, EdiConfig(every=every, max_fps=max_fps), [out.append])
            for p in packets:  # all in before the worker starts: its chunks are as large as they get
                assert ring.push(p, timeout_s=5)
            ring.close()
            worker.start()
            assert worker.done.wait(30) and worker.error is None
            assert worker.skipped_max_fps == 0 and ring.history_truncated == 0
            sent[max_fps] = out
            # frames are handed on at most 32 at a time: memory stays bounded at any --every
            assert (max(batches) == 32) if max_fps is None and every == 7 else (max(batches, default=0) <= 32)
        _assert_same_frames(sent[None], sent[1e12])


def _assert_same_frames(batched, single):
    assert sum(r.kind == "latent" for r in batched) > 50
    assert [(r.kind, r.t_us, r.n_events, r.ref_t_us, r.arrival_ns) for r in batched] == \
           [(r.kind, r.t_us, r.n_events, r.ref_t_us, r.arrival_ns) for r in single]
    for a, b in zip(batched, single):
        np.testing.assert_array_equal(a.image, b.image)


def test_a_gap_while_a_frame_is_deblurred_on_the_helper_thread():
    """Live data lost while the helper thread deblurs: the next APS frame must be deblurred on the original
    reconstructor (never on the streaming copy), and the original must learn of the gap (no consistency pair
    across it)."""
    import time

    from tests.edi_live.edi_scenes import make_scene

    from edi_live.reconstructor import EdiReconstructor

    class SlowDeblur(EdiReconstructor):
        gaps_seen = 0

        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            if self.has_reference and not self._streamer:
                time.sleep(0.3)  # a slow deblur: the gap and the next frame arrive meanwhile
            return super().on_frame(frame, events, arrival_ns, ready=ready)

        def mark_gap(self):
            if not self._streamer:
                SlowDeblur.gaps_seen += 1
            super().mark_gap()

    scene = make_scene("brick", c_on=0.25, width=80, height=60, n_frames=4, sigma_c=0.02, seed=3)
    t = scene.events["t"]
    packets, cut = [], 0
    for k, f in enumerate(scene.frames):
        end = int(np.searchsorted(t, f.exposure_end_us, side="right")) + 10
        packets.append(Packet(events=scene.events[cut:end], frames=[f], gap=(k == 2)))
        cut = end
    packets.append(Packet(events=scene.events[cut:]))
    ring = EventRing(capacity_events=1 << 20, capacity_frames=16, policy="wait")
    for p in packets:
        assert ring.push(p, timeout_s=5)
    ring.close()
    out, errors = [], []
    worker = EdiWorker(ring, SlowDeblur(scene.width, scene.height), EdiConfig(every=500, deblur_thread=True),
                       [out.append], on_error=errors.append)
    worker.start()
    assert worker.done.wait(30)
    assert not errors, errors
    assert worker.sent["deblurred"] == 4 and not worker.rec._streamer
    assert SlowDeblur.gaps_seen >= 1, "the original reconstructor never heard of the gap"


class SettleLog(StandIn):
    """Records, at each settle(), the deblurred frames sent so far; settle() after the second APS frame waits
    until `release` is set (the sink sets it), so the test sees what the worker does meanwhile."""

    def __init__(self, sent: list, release: threading.Event | None = None) -> None:
        super().__init__()
        self.sent, self.release = sent, release
        self.at_settle: list[list[int]] = []
        self.released: bool | None = None

    def settle(self):
        super().settle()
        self.at_settle.append([r.t_us for r in self.sent if r.kind == "deblurred"])
        if self.release is not None and len(self.frames_given) == 2:
            self.released = self.release.wait(10)  # a handshake with the sink, not a pause


def test_inline_the_deblurred_frame_is_sent_before_settle_runs():
    ev, frames, packets = two_frame_packets()
    out: list = []
    rec = SettleLog(out)
    worker = stream_to_the_end(rec, EdiConfig(every=400, deblur_thread=False), packets, [out.append])
    f1, f2 = frames[0].mid_exposure_us, frames[1].mid_exposure_us
    assert rec.settled == 2 and rec.at_settle == [[f1], [f1, f2]], "each settle() after its frame was sent"
    assert [r.t_us for r in out if r.kind == "deblurred"] == [f1, f2]


def test_deblur_thread_sends_the_deblurred_frame_before_settle_and_only_once():
    """The helper thread's settle() (after the second frame) blocks until the sink has seen the deblurred frame
    and then a latent frame: the frame left before settle(), and latent frames kept coming from the copy."""
    ev, frames, packets = two_frame_packets()
    f1, f2 = frames[0].mid_exposure_us, frames[1].mid_exposure_us
    out: list = []
    deblurred_sent, release = threading.Event(), threading.Event()
    after: list[Reconstruction] = []

    def sink(r: Reconstruction) -> None:
        out.append(r)
        if r.kind == "deblurred" and r.t_us == f2:
            deblurred_sent.set()
        elif deblurred_sent.is_set() and r.kind == "latent" and not release.is_set():
            after.append(r)
            release.set()

    ring = EventRing(capacity_events=1 << 16, policy="wait")
    rec = SettleLog(out, release)
    worker = EdiWorker(ring, rec, EdiConfig(every=400, deblur_thread=True), [sink])
    worker.start()
    t = ev["t"]
    head = [p for p in packets if p.events.size and int(p.events["t"][0]) <= frames[1].exposure_end_us + 4_000]
    for p in head:
        assert ring.push(p, timeout_s=5)
    assert deblurred_sent.wait(10), "the deblurred frame was not sent while settle() was pending"
    for p in packets[len(head):]:
        assert ring.push(p, timeout_s=5)
    ring.close()
    assert worker.done.wait(10) and worker.error is None
    assert rec.released is True, "settle() ran before the deblurred frame was sent"
    assert after and after[0].ref_t_us == f1, "latent frames came from the copy while the original settled"
    assert [r.t_us for r in out if r.kind == "deblurred"] == [f1, f2], "each deblurred frame exactly once"
    assert worker.sent["deblurred"] == 2 and rec.settled == 2 and worker.rec is rec
    assert int(np.sum(t > frames[0].exposure_end_us)) == rec.events_applied


class SignalRing(EventRing):
    """Once `armed`, sets `signal` when the worker waits for data or takes the frame starting at `watch_us`."""

    def __init__(self, watch_us: int, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.watch_us, self.armed, self.signal = watch_us, False, threading.Event()

    def wait(self, since_version: int, timeout_s: float, wake=None) -> bool:
        if self.armed:
            self.signal.set()
        return super().wait(since_version, timeout_s, wake)

    def pop_frame(self):
        entry = super().pop_frame()
        if self.armed and entry is not None and entry.frame.exposure_start_us == self.watch_us:
            self.signal.set()
        return entry


def test_a_clock_offset_moved_by_settle_on_the_helper_thread_holds_for_the_next_frame():
    """settle() of the second frame (on the helper thread) moves the offset to 3 ms while the worker streams on
    the copy (which keeps 0) up to the third frame. The third frame must then be gated and cut with the
    original's new offset: its event-clock window [43000, 45000] complete, nothing before 43000."""
    offset = 3000
    frames = [aps(0, 2_000), aps(20_000, 22_000), aps(40_000, 42_000)]
    ev = events_at(np.arange(0, 80_000, 5))
    ring = SignalRing(40_000, capacity_events=1 << 16, capacity_frames=16, policy="wait")
    for p in packets_by_frame(ev, frames):
        assert ring.push(p, timeout_s=5)
    ring.close()

    class MovesOffset(StandIn):
        def settle(self):
            super().settle()
            if len(self.frames_given) == 2:
                self.clock_offset_us = offset
                ring.armed = True  # the worker now takes the third frame, or waits for this settle()
                assert ring.signal.wait(10)

    rec, errors = MovesOffset(), []
    worker = EdiWorker(ring, rec, EdiConfig(every=400, deblur_thread=True), [], on_error=errors.append)
    worker.start()
    assert worker.done.wait(20) and not errors, errors
    frame, given = rec.frames_given[2]
    t = given["t"]
    assert t.min() >= 43_000 and t.max() > 45_000, (t.min(), t.max())
    assert np.all(np.isin(ev["t"][(ev["t"] >= 43_000) & (ev["t"] <= 45_000)], t))


def test_the_deblurred_frame_is_sent_while_on_frame_still_readies_its_state():
    """On the helper thread the deblurred frame goes out as soon as on_frame hands it to `ready`, not when
    on_frame returns: here on_frame returns only once the worker has sent that frame (bounded wait, no sleep)."""
    sent = threading.Event()
    seen_before_return = []

    class ReadyEarly(StandIn):
        def on_frame(self, frame, events, arrival_ns=0, ready=None):
            rec = super().on_frame(frame, events, arrival_ns)
            if ready is not None and len(self.frames_given) == 2:  # the second frame: on the helper thread
                ready(rec)
                seen_before_return.append(sent.wait(10))
            return rec

    def sink(rec):
        if rec.kind == "deblurred" and rec.t_us == aps(20_000, 22_000).mid_exposure_us:
            sent.set()

    ev, frames, packets = two_frame_packets()
    worker = stream_to_the_end(ReadyEarly(), EdiConfig(every=400, deblur_thread=True), packets, [sink])
    assert worker.error is None
    assert seen_before_return == [True]


def test_a_reconstructor_without_the_ready_seam_still_deblurs_on_the_helper_thread():
    """A Reconstructor written before on_frame took `ready` (a plugged-in reconstructor_factory) keeps working with
    the deblur thread: its frame leaves when on_frame returns."""
    class OldProtocol(StandIn):
        def on_frame(self, frame, events, arrival_ns=0):
            return super().on_frame(frame, events, arrival_ns)

    _, frames, packets = two_frame_packets()
    for threaded in (False, True):
        worker, rec, out, errors = run_worker(packets, EdiConfig(every=400, deblur_thread=threaded),
                                              rec=OldProtocol())
        assert not errors, errors
        assert sum(r.kind == "deblurred" for r in out) == len(frames)
