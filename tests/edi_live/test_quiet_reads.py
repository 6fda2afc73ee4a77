"""The worker's quiet reads (edi_live.quiet_reads): a still camera's noise is read in steps of several packets,
and a motion onset still makes a frame promptly, in sensor time.

The worker-level tests replay a simulated still camera (0.5 events/s per pixel of noise, APS at 20 fps) that
starts moving after 1 s, in 1 ms packets pushed in lockstep with the worker (EventRing.wait_consumer_idle): each
packet goes in once the worker has done everything it will do with the ones before, so what the worker reads
per wake-up, and how far the sensor clock had got when a frame went out, do not depend on this machine's speed.
Oracles: the simulator's labels (which events are noise, the first moving event) and the packets pushed.
"""

from __future__ import annotations

import math

import numpy as np

from edi_live.datatypes import EVENT_DTYPE, Frame, Packet
from edi_live.quiet_reads import MAX_BATCH_US, MIN_BATCH_US, QuietReads
from edi_live.ring import EventChunk, EventRing
from edi_live.ring_wake import WakeWhen
from tests.helpers.recordings import events_at_random_pixels
from tools.stream_noise import noisy_scene, onset_delay_us


class ReadCountingRing(EventRing):
    """Records the ring's watermark (sensor time) at every read that returned events."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.reads_at_us: list[int] = []

    def read_events(self, max_n: int, until_index: int | None = None,
                    through_t_us: int | None = None) -> EventChunk:
        chunk = super().read_events(max_n, until_index, through_t_us)
        if len(chunk.events):
            self.reads_at_us.append(self.watermark_us)
        return chunk


def test_a_noisy_still_scene_is_read_in_steps_of_several_packets_and_an_onset_makes_a_frame_within_a_step():
    ring = ReadCountingRing(capacity_events=1 << 22, capacity_frames=256, policy="wait")
    delay_us = onset_delay_us(ring=ring)  # also checks: every event read, no frame on the still part
    events, _, onset_us = noisy_scene(1.3, onset_s=1.0)
    still_reads = sum(t < onset_us for t in ring.reads_at_us)
    packets = (onset_us - int(events["t"][0])) // 1000  # 1 ms packets before the onset
    # at most 4 reads per 50 ms APS period: two quiet steps of half the period, the events up to the APS frame and
    # the rest after it (123 reads with steps of a fifth of it)
    assert packets > 900 and still_reads <= 4 * packets // 50, f"{still_reads} reads for {packets} packets of noise"
    # the onset is read within one quiet step at most (25 ms at 20 fps), under the 50 ms frame period
    assert 0 <= delay_us < MAX_BATCH_US


def test_an_aps_frame_waiting_for_its_late_events_does_not_make_the_still_scene_read_per_packet():
    # with the events 8 ms late (a real camera's clock offset) each APS frame waits for its window's late events;
    # the worker then wakes once the sensor time is past them, not on every packet (312 still reads before)
    ring = ReadCountingRing(capacity_events=1 << 22, capacity_frames=256, policy="wait")
    delay_us = onset_delay_us(ring=ring, clock_offset_us=8_000)
    events, _, onset_us = noisy_scene(1.3, onset_s=1.0)
    still_reads = sum(t < onset_us for t in ring.reads_at_us)
    packets = (onset_us - int(events["t"][0])) // 1000
    assert packets > 900 and still_reads < packets / 4, f"{still_reads} reads for {packets} packets of noise"
    assert 0 <= delay_us < MAX_BATCH_US
    # once the noise rate is known, per 50 ms APS period: one read up to the frame and through its late window once
    # they are in (the frame does not wake the worker before), one with the first event after that window when the
    # window ends at a packet's end, and one quiet step; what came after the frame waits for that step (75 reads
    # when it was read at once, 61 when the frame woke the worker and its window was a read of its own)
    settled_us = int(events["t"][0]) + 200_000
    periods = (onset_us - settled_us) / 50_000
    steady = sum(settled_us <= t < onset_us for t in ring.reads_at_us)
    assert steady <= 3 * periods, f"{steady} reads in {periods:.1f} APS periods"


def test_an_onset_wakes_the_worker_by_its_excess_over_the_noise_so_far_not_over_a_whole_step():
    # the count that ends a quiet step early is what the noise gives in the whole step plus a margin; an onset early
    # in the step had to make up the rest of the step's noise too (6.8 ms for two of these three onsets)
    assert all(onset_delay_us(seed_shift=k) < MAX_BATCH_US / 4 for k in range(3))


def test_the_rate_condition_compares_the_events_pushed_with_the_rate_over_the_time_so_far():
    wake = WakeWhen(head=10_000, t_us=100_000, rate_per_us=0.02, head0=1000, t0_us=0, slack=50.0)
    assert not wake.met(head=1000 + 55, watermark_us=250)  # 5 expected in 250 µs, 50 more: not yet
    assert wake.met(head=1000 + 56, watermark_us=250)
    assert not wake.met(head=1000 + 150, watermark_us=5000)  # 100 expected by then
    assert wake.met(head=0, watermark_us=100_000) and wake.met(head=10_000, watermark_us=0)  # the step's own bounds
    assert not WakeWhen(head=10_000, t_us=100_000).met(head=5000, watermark_us=10)  # no rate: no such condition


def test_a_large_every_does_not_delay_the_onset():
    assert onset_delay_us(seed_shift=3, every=20_000) < MAX_BATCH_US


def _ring_withevents_at_random_pixels(rate_per_ms: int, ms: int) -> EventRing:
    ring = EventRing(capacity_events=1 << 16, policy="wait")
    for k in range(ms):
        ev = np.zeros(rate_per_ms, EVENT_DTYPE)
        ev["t"] = k * 1000 + np.arange(rate_per_ms)
        ring.push(Packet(events=ev, watermark_us=k * 1000 + 999))
    ring.read_events(1 << 20)  # the worker waits once it has read everything
    return ring


def test_the_quiet_step_is_half_the_aps_period_within_bounds():
    quiet = QuietReads(every=1000)
    assert quiet.batch_us == MAX_BATCH_US  # before any APS period is known
    for period_us, want in ((50_000, 25_000), (20_000, 10_000), (1_000, MIN_BATCH_US), (500_000, MAX_BATCH_US)):
        quiet = QuietReads(every=1000)
        for k in range(3):
            quiet.on_aps_frame(Frame(np.zeros((2, 2), np.uint8), k * period_us, k * period_us + 100))
        assert quiet.batch_us == want


def test_the_wake_count_follows_the_noise_rate_and_an_active_scene_is_not_batched():
    ring = _ring_withevents_at_random_pixels(rate_per_ms=20, ms=100)
    quiet = QuietReads(every=1000)
    assert quiet.wake(ring, quiet=False) is None
    first = quiet.wake(ring, quiet=True)
    assert first.t_us == ring.watermark_us + MAX_BATCH_US
    assert first.head - ring.head < 20  # the rate is not known yet: about a packet
    for k in range(100, 200, 10):  # quiet waits 10 ms apart at 20 events/ms
        ev = np.zeros(200, EVENT_DTYPE)
        ev["t"] = k * 1000 + np.arange(200) * 50
        ring.push(Packet(events=ev, watermark_us=k * 1000 + 9_999))
        ring.read_events(1 << 20)
        wake = quiet.wake(ring, quiet=True)
    expected = 20 * MAX_BATCH_US / 1000  # events the noise gives in one step
    count = wake.head - ring.head
    assert expected + 2 * math.sqrt(expected) < count < expected + 6 * math.sqrt(expected) + 20
    small = QuietReads(every=10)
    assert small.wake(ring, quiet=True).head - ring.head <= 10  # never past a latent frame
    ring.push(Packet(events=ev[:5], watermark_us=300_000))  # pushed after the worker's last read: they count
    assert small.wake(ring, quiet=True).head == ring.read_index + 10 == ring.head + 5


def _still_scene_through_a_small_ring(policy: str) -> tuple[EventRing, object, int, bool]:
    from edi_live.config import EdiConfig
    from edi_live.node import default_reconstructor
    from edi_live.worker import EdiWorker
    from tools.stream_noise import scene_packets

    events, frames, _ = noisy_scene(1.5)
    ring = EventRing(capacity_events=1024, capacity_frames=16, policy=policy)  # the smallest --ring-events
    worker = EdiWorker(ring, default_reconstructor(240, 180, EdiConfig(clock_offset_us=0)), EdiConfig(heartbeat_s=3600))
    worker.start()
    pushed_all = True
    try:
        for p in scene_packets(events, frames):
            if not ring.push(p, timeout_s=10):  # a bound, not a synchronisation: the producer gave up
                pushed_all = False
                break
            if policy == "drop_oldest":
                assert ring.wait_consumer_idle(10)  # live pace: the next packet once the worker is idle
    finally:
        ring.close()
        worker.done.wait(30)
    return ring, worker, len(events), pushed_all


def test_a_replay_of_a_still_scene_through_the_smallest_ring_does_not_stall():
    """A quiet step of more events than the ring lets pile up unread never came: the producer waited for room,
    the worker for the step (a hang at --ring-events 1024)."""
    ring, worker, n, pushed_all = _still_scene_through_a_small_ring("wait")
    assert pushed_all and worker.events_in == n


def test_a_live_still_scene_through_the_smallest_ring_loses_no_events():
    ring, worker, n, _ = _still_scene_through_a_small_ring("drop_oldest")
    assert ring.dropped_events == 0 and worker.events_in == n


def test_a_quiet_step_the_worker_was_woken_for_is_read_even_after_an_aps_frame():
    """The worker takes an APS frame with nothing unread after it, waits with the quiet step and is woken once the
    step is met: defer() must not start another step and send it back to sleep (an onset's wake was lost)."""
    rng = np.random.default_rng(0)
    ring = EventRing(capacity_events=1 << 16, policy="wait")
    quiet = QuietReads(every=1000)
    t = 0
    for _ in range(3):  # a known noise rate: 20 events per 1 ms packet
        ring.push(Packet(events=events_at_random_pixels(np.linspace(t, t + 999, 20).astype(np.int64), rng), watermark_us=t + 999))
        ring.read_events(1 << 16)
        quiet.wake(ring, quiet=True)
        t += 1000
    quiet.on_aps_frame(Frame(np.zeros((4, 4), np.uint8), 0, t))  # taken; nothing unread after it
    wake = quiet.wake(ring, quiet=True)
    while not wake.met(ring.head, ring.watermark_us):  # noise until the step is over (the ring would wake it)
        ring.push(Packet(events=events_at_random_pixels(np.linspace(t, t + 999, 20).astype(np.int64), rng), watermark_us=t + 999))
        t += 1000
    assert not quiet.defer(ring), "woken for a step that is met, the worker went back to sleep"


def test_a_source_that_pauses_leaves_no_quiet_events_unread():
    """A live camera that stops sending without closing: the quiet step is never met, but the events that came
    are read once a wait passed without a push (they stayed unread until the next push)."""
    rng = np.random.default_rng(1)
    ring = EventRing(capacity_events=1 << 16, policy="wait")
    quiet = QuietReads(every=1000)
    t = 0
    for _ in range(4):
        ring.push(Packet(events=events_at_random_pixels(np.linspace(t, t + 999, 20).astype(np.int64), rng), watermark_us=t + 999))
        ring.read_events(1 << 16)
        quiet.wake(ring, quiet=True)
        t += 1000
    ring.push(Packet(events=events_at_random_pixels(np.linspace(t, t + 999, 20).astype(np.int64), rng), watermark_us=t + 999))
    assert quiet.defer(ring), "a step under way: the new packet waits for it"
    quiet.wake(ring, quiet=True)  # the worker waits; nothing comes, the wait times out
    assert not quiet.defer(ring), "nothing came since the worker went to wait: read what is there"
