"""EventRing: windows, wraparound, overrun accounting, the wait policy, frame placement, producer/consumer stress.

Oracles are the input arrays themselves (what went in, in order) and brute-force boolean masks for windows.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from edi_live.datatypes import EVENT_DTYPE, Frame, Packet
from edi_live.ring import EventRing
from edi_live.ring_wake import WakeWhen
from tests.helpers.recordings import events_at_random_pixels




def concat(parts: list[np.ndarray]) -> np.ndarray:
    # np.concatenate of a padded structured dtype returns a packed dtype; concatenate the raw bytes instead
    if not parts:
        return np.zeros(0, EVENT_DTYPE)
    return np.concatenate([p.view(np.uint8) for p in parts]).view(EVENT_DTYPE)


def frame(t0: int, t1: int) -> Frame:
    return Frame(np.zeros((4, 4), np.uint8), exposure_start_us=t0, exposure_end_us=t1)


def drain(ring: EventRing, max_n: int = 1000) -> np.ndarray:
    parts = []
    while True:
        chunk = ring.read_events(max_n)
        if len(chunk.events) == 0:
            break
        parts.append(chunk.events)
    return concat(parts)


def test_reads_return_exactly_what_was_pushed_across_wraparound(rng):
    ring = EventRing(capacity_events=64, policy="wait")
    t = np.cumsum(rng.integers(0, 5, 1000))
    ev = events_at_random_pixels(t, rng)
    got = []
    for start in range(0, 1000, 20):  # 20 per push, read in odd sizes: crosses the wrap many times
        assert ring.push(Packet(events=ev[start:start + 20]), timeout_s=1.0)
        got.append(ring.read_events(7).events)
        got.append(ring.read_events(13).events)
    got.append(drain(ring))
    got = concat(got)
    assert got.dtype == EVENT_DTYPE
    np.testing.assert_array_equal(got, ev)


def test_a_read_through_a_time_stops_at_the_first_later_event_across_wraparound(rng):
    ring = EventRing(capacity_events=64, policy="wait")
    t = np.cumsum(rng.integers(0, 3, 600))  # repeated times: the stop is after the first event later than the bound
    ev = events_at_random_pixels(t, rng)
    got = []
    for start in range(0, 600, 30):  # 30 per push into 64 slots: the reads cross the wrap many times
        assert ring.push(Packet(events=ev[start:start + 30]), timeout_s=1.0)
        pushed = ev[start:start + 30]
        bound = int(pushed["t"][0]) + int(rng.integers(-2, 40))
        chunk = ring.read_events(1000, None, bound).events
        later = np.flatnonzero(pushed["t"] > bound)
        np.testing.assert_array_equal(chunk, pushed[: later[0] + 1] if later.size else pushed)
        got += [chunk, drain(ring)]
    np.testing.assert_array_equal(concat(got), ev)


def test_read_is_a_copy_not_a_view(rng):
    ring = EventRing(capacity_events=32, policy="drop_oldest")
    ev = events_at_random_pixels(np.arange(16), rng)
    ring.push(Packet(events=ev))
    chunk = ring.read_events(16)
    before = chunk.events.copy()
    for k in range(10):  # overwrite every slot several times
        ring.push(Packet(events=events_at_random_pixels(np.arange(16) + 100 * (k + 1), rng)))
    np.testing.assert_array_equal(chunk.events, before)


@pytest.mark.parametrize("t0,t1", [(0, 10), (17, 18), (250, 700), (-5, 10_000), (300, 300), (999, 1001)])
def test_window_matches_brute_force_mask_after_wrap(rng, t0, t1):
    ring = EventRing(capacity_events=512, policy="wait")
    t = np.sort(rng.integers(0, 1000, 2000))
    ev = events_at_random_pixels(t, rng)
    for start in range(0, 2000, 100):
        ring.push(Packet(events=ev[start:start + 100]), timeout_s=1.0)
        drain(ring, 37)
    retained = ev[2000 - 512:]  # the ring holds the last `capacity` events
    expected = retained[(retained["t"] >= t0) & (retained["t"] < t1)]
    np.testing.assert_array_equal(ring.window(t0, t1), expected)


def test_window_stops_at_the_read_cursor(rng):
    ring = EventRing(capacity_events=256, policy="wait")
    ev = events_at_random_pixels(np.arange(100), rng)
    ring.push(Packet(events=ev))
    ring.read_events(40)
    np.testing.assert_array_equal(ring.window(0, 1000), ev[:40])
    np.testing.assert_array_equal(ring.window(0, 1000, end_index=100), ev)


def test_a_window_past_the_retained_history_is_counted_and_said_once(rng, caplog):
    """An exposure that started before the oldest event the ring still holds is cut short: counted, and one
    warning line naming the flag (the summary gives the count)."""
    ring = EventRing(capacity_events=256, policy="wait")
    ev = events_at_random_pixels(np.arange(1000), rng)
    for start in range(0, 1000, 100):
        ring.push(Packet(events=ev[start:start + 100]), timeout_s=1.0)
        drain(ring)
    with caplog.at_level("WARNING", logger="edi_live.ring"):
        assert ring.window(1000 - 256, 2000).size == 256 and ring.history_truncated == 0  # all still held
        got = ring.window(500, 2000)
        ring.window(600, 2000)
    np.testing.assert_array_equal(got, ev[1000 - 256:])
    assert ring.history_truncated == 2
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "--ring-events" in warnings[0].getMessage()


def test_frame_end_index_is_just_past_its_exposure(rng):
    ring = EventRing(capacity_events=256, policy="wait")
    ev = events_at_random_pixels(np.arange(0, 100, 2), rng)  # t = 0, 2, ..., 98
    f = frame(10, 41)
    ring.push(Packet(events=ev, frames=[f]))
    entry = ring.peek_frame()
    assert entry.frame is f
    assert entry.end_index == int(np.sum(ev["t"] <= 41))  # brute force: events up to exposure end
    chunk = ring.read_events(1000, until_index=entry.end_index)
    assert chunk.events["t"].max() <= 41
    assert len(ring.read_events(1000).events) == 0  # queued at the cursor: taken before any later event
    ring.pop_frame()
    assert ring.read_events(1000).events["t"].min() > 41


def test_a_frame_queued_at_the_read_cursor_after_the_consumers_look_stops_its_next_read(rng):
    # The consumer has read every event and finds no frame queued. Then a packet comes whose events all lie past
    # the frame it carries (a replay sends a frame with the packet that passed its exposure end): the frame is
    # queued exactly at the cursor. The next read must not take the events past it, or the frame would be
    # deblurred after them in this run and before them in a run where the frame came before the look.
    ring = EventRing(capacity_events=256, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(0, 50), rng)))
    assert len(ring.read_events(1000).events) == 50
    assert ring.peek_frame() is None  # the worker's look: nothing queued
    ring.push(Packet(events=events_at_random_pixels(np.arange(60, 100), rng), frames=[frame(10, 55)]))
    assert ring.peek_frame().end_index == ring.read_index == 50
    assert len(ring.read_events(1000).events) == 0, "no event past a queued frame's exposure end"
    ring.pop_frame()
    assert len(ring.read_events(1000).events) == 40


def test_a_read_through_the_late_window_of_a_frame_at_the_cursor_goes_on(rng):
    # the worker's read for a frame it holds (its late window in the event clock) is not stopped by that frame
    ring = EventRing(capacity_events=256, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(0, 100), rng), frames=[frame(10, 49)]))
    entry = ring.peek_frame()
    ring.read_events(1000, entry.end_index)
    assert ring.read_index == entry.end_index
    np.testing.assert_array_equal(ring.read_events(1000, None, 60).events["t"], np.arange(50, 62))


def test_drop_oldest_never_blocks_and_counts_every_dropped_event(rng):
    ring = EventRing(capacity_events=100, policy="drop_oldest")  # at most 50 unread
    ev = events_at_random_pixels(np.arange(1000), rng)
    for start in range(0, 1000, 30):
        assert ring.push(Packet(events=ev[start:start + 30]), timeout_s=0)  # never waits, even with timeout 0
    got = drain(ring)
    assert len(got) + ring.dropped_events == 1000
    np.testing.assert_array_equal(got, ev[1000 - len(got):])  # the newest survive, in order
    assert ring.stats()["ring_dropped_events"] == ring.dropped_events > 0


def test_drop_oldest_marks_the_gap_on_the_next_read(rng):
    ring = EventRing(capacity_events=100, policy="drop_oldest")
    ring.push(Packet(events=events_at_random_pixels(np.arange(40), rng)))
    first = ring.read_events(10)
    assert not first.gap
    ring.push(Packet(events=events_at_random_pixels(np.arange(40, 80), rng)))  # 30 + 40 unread > 50: 20 dropped
    chunk = ring.read_events(100)
    assert chunk.gap
    assert ring.dropped_events == 20
    assert not ring.read_events(10).gap  # the mark is consumed once


def test_oversized_burst_keeps_its_newest_part(rng):
    ring = EventRing(capacity_events=100, policy="drop_oldest")
    ev = events_at_random_pixels(np.arange(500), rng)
    ring.push(Packet(events=ev))
    got = drain(ring)
    np.testing.assert_array_equal(got, ev[-50:])
    assert ring.dropped_events == 450


def test_packet_gap_flag_reaches_the_consumer(rng):
    ring = EventRing(capacity_events=100, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(5), rng)))
    ring.push(Packet(events=events_at_random_pixels(np.arange(5, 10), rng), gap=True))
    assert not ring.read_events(5).gap
    assert ring.read_events(5).gap


def test_frame_queue_drop_oldest_counts(rng):
    ring = EventRing(capacity_events=100, capacity_frames=2, policy="drop_oldest")
    for k in range(5):
        ring.push(Packet(frames=[frame(k * 10, k * 10 + 5)]))
    assert ring.dropped_frames == 3
    assert ring.pop_frame().frame.exposure_start_us == 30
    assert ring.pop_frame().frame.exposure_start_us == 40
    assert ring.pop_frame() is None


def test_wait_policy_times_out_when_full_and_resumes_after_a_read(rng):
    ring = EventRing(capacity_events=100, policy="wait")
    ev = events_at_random_pixels(np.arange(80), rng)
    assert ring.push(Packet(events=ev[:50]), timeout_s=0.5)
    assert not ring.push(Packet(events=ev[50:60]), timeout_s=0.05)  # full: times out
    assert ring.dropped_events == 0
    assert ring.producer_wait_s > 0
    ring.read_events(30)
    assert ring.push(Packet(events=ev[50:80]), timeout_s=0.5)
    np.testing.assert_array_equal(drain(ring), ev[30:80])


def test_wait_policy_frame_queue_times_out(rng):
    ring = EventRing(capacity_events=100, capacity_frames=1, policy="wait")
    assert ring.push(Packet(frames=[frame(0, 1)]), timeout_s=0.5)
    assert not ring.push(Packet(frames=[frame(2, 3)]), timeout_s=0.05)
    ring.pop_frame()
    assert ring.push(Packet(frames=[frame(2, 3)]), timeout_s=0.5)


def test_close_releases_a_waiting_producer_and_ends_the_consumer(rng):
    ring = EventRing(capacity_events=100, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(50), rng)))
    result = {}
    producer = threading.Thread(target=lambda: result.setdefault("ok", ring.push(
        Packet(events=events_at_random_pixels(np.arange(50, 60), rng)), timeout_s=5)))
    producer.start()
    ring.close()
    producer.join(timeout=2)
    assert not producer.is_alive()
    assert result["ok"] is False
    assert not ring.exhausted  # 50 unread events still to drain
    assert len(drain(ring)) == 50
    assert ring.exhausted


def test_wait_returns_on_new_data_and_times_out_otherwise(rng):
    ring = EventRing(capacity_events=100, policy="wait")
    v = ring.version
    assert not ring.wait(v, timeout_s=0.02)
    ring.push(Packet(events=events_at_random_pixels(np.arange(3), rng)))
    assert ring.wait(v, timeout_s=0.02)


class WaitingConsumer:
    """A consumer thread blocked in ring.wait with a WakeWhen; `woke_at` is (head, watermark) when it returned."""

    def __init__(self, ring: EventRing, wake: WakeWhen) -> None:
        self.woke_at: tuple[int, int] | None = None
        version = ring.version

        def run() -> None:
            ring.wait(version, 30.0, wake)
            self.woke_at = (ring.head, ring.watermark_us)

        self.thread = threading.Thread(target=run)
        self.thread.start()
        assert ring.wait_consumer_idle(10)


@pytest.mark.parametrize("wake_by", ["events", "sensor time", "aps frame", "close"])
def test_a_consumer_waiting_with_a_wake_condition_sleeps_through_pushes_that_do_not_meet_it(rng, wake_by):
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    consumer = WaitingConsumer(ring, WakeWhen(head=100, t_us=10_000))
    for k in range(9):  # 90 events up to t = 899 µs: below both thresholds
        ring.push(Packet(events=events_at_random_pixels(np.arange(100 * k, 100 * k + 10), rng), watermark_us=100 * k + 99))
        assert ring.wait_consumer_idle(10), "still waiting (the condition is not met)"
        assert consumer.woke_at is None
    last = {"events": Packet(events=events_at_random_pixels(np.arange(900, 910), rng)),
            "sensor time": Packet(events=events_at_random_pixels(np.array([10_000]), rng)),
            "aps frame": Packet(frames=[frame(900, 950)], watermark_us=950)}.get(wake_by)
    ring.push(last) if last is not None else ring.close()
    consumer.thread.join(10)
    assert consumer.woke_at is not None
    assert not ring.wait_consumer_idle(0.01)  # nobody waits any more


def test_a_frame_the_consumer_has_seen_does_not_wake_it_again_but_a_new_one_does(rng):
    # The worker holds an APS frame until its late events are in: while it waits for them with `frames=1`, pushes
    # that meet nothing else leave it asleep (before, the queued frame made every push wake it)
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(0, 10), rng), frames=[frame(0, 5)], watermark_us=99))
    consumer = WaitingConsumer(ring, WakeWhen(head=1000, t_us=10_000, frames=1))
    for k in range(1, 5):
        ring.push(Packet(events=events_at_random_pixels(np.arange(100 * k, 100 * k + 10), rng), watermark_us=100 * k + 99))
        assert ring.wait_consumer_idle(10), "still waiting (one frame queued, the one it has seen)"
        assert consumer.woke_at is None
    ring.push(Packet(frames=[frame(500, 550)], watermark_us=550))
    consumer.thread.join(10)
    assert consumer.woke_at == (50, 550)


def test_a_new_frame_with_late_events_wakes_the_consumer_once_the_watermark_is_past_them(rng):
    # a quiet worker cannot deblur an APS frame before its late events (the clock offset) are in: waking it at the
    # frame's push only made a read of the events up to the frame, and another for the late window
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    consumer = WaitingConsumer(ring, WakeWhen(head=1000, t_us=10_000, frame_late_us=300))
    ring.push(Packet(events=events_at_random_pixels(np.arange(0, 10), rng), frames=[frame(0, 50)], watermark_us=99))
    for k in range(1, 4):  # the watermark reaches 350 = exposure end + 300: not past it
        events = events_at_random_pixels(np.arange(100 * k, 100 * k + 10), rng)
        ring.push(Packet(events=events, watermark_us=min(350, 100 * k + 99)))
        assert ring.wait_consumer_idle(10), "still waiting (the frame's late events are not in)"
        assert consumer.woke_at is None
    ring.push(Packet(events=events_at_random_pixels(np.array([351]), rng), watermark_us=351))
    consumer.thread.join(10)
    assert consumer.woke_at == (41, 351)


def test_a_read_through_a_late_window_goes_past_the_first_frame_but_not_the_next(rng):
    # the quiet worker reads the events up to its next APS frame and the frame's late window in one read
    ring = EventRing(capacity_events=256, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(0, 100), rng), frames=[frame(10, 29), frame(40, 69)]))
    first, second = ring._frames[0], ring._frames[1]
    assert ring.read_index < first.end_index
    np.testing.assert_array_equal(ring.read_events(1000, None, 50).events["t"], np.arange(0, 52))
    assert ring.read_index > first.end_index
    np.testing.assert_array_equal(ring.read_events(1000, None, 90).events["t"], np.arange(52, 70))  # second's end
    assert ring.read_index == second.end_index


def test_a_wait_with_a_condition_already_met_returns_at_once(rng):
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    v = ring.version
    ring.push(Packet(events=events_at_random_pixels(np.arange(50), rng)))
    assert ring.wait(v, 10.0, WakeWhen(head=50, t_us=10**9))
    assert not ring.wait(ring.version, 0.01, WakeWhen(head=0, t_us=0))  # nothing new since: times out


def test_a_poke_between_the_consumers_look_and_its_wait_is_not_lost(rng):
    # The deblur helper pokes the worker when its frame is ready. The worker reads `version`, finds nothing to do,
    # and then waits with its quiet-scene condition: a poke that came in between must end that wait at once, as
    # a frame or close would, not after the condition's events, sensor time or the timeout.
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    v = ring.version
    ring.poke()  # the helper thread, just before the worker's wait

    def must_not_block(timeout=None):
        raise AssertionError("the wait blocked after a poke it had not seen")

    ring._cond.wait = must_not_block
    assert ring.wait(v, 30.0, WakeWhen(head=1000, t_us=10**9))
    del ring._cond.wait  # the poke is used up: the next wait blocks as before
    assert not ring.wait(ring.version, 0.01, WakeWhen(head=1000, t_us=10**9))


def test_arrival_time_of_the_last_included_event(rng):
    ring = EventRing(capacity_events=100, policy="wait")
    for k in range(3):
        ring.push(Packet(events=events_at_random_pixels(np.arange(10 * k, 10 * k + 10), rng), arrival_ns=1000 + k))
    chunk = ring.read_events(25)
    assert chunk.arrival_ns_at(10) == 1000  # event 9 came with push 0
    assert chunk.arrival_ns_at(11) == 1001
    assert chunk.arrival_ns_at(25) == 1002
    assert ring.read_events(5).arrival_ns_at(5) == 1002


@pytest.mark.parametrize("policy", ["wait", "drop_oldest"])
def test_stress_one_producer_one_consumer(rng, policy):
    ring = EventRing(capacity_events=4096, capacity_frames=4, policy=policy)
    n_packets, per_packet = 400, 97
    t = np.arange(n_packets * per_packet, dtype=np.int64)
    ev = events_at_random_pixels(t, rng)
    frames_in = [frame(int(k * per_packet), int(k * per_packet + 50)) for k in range(0, n_packets, 10)]
    errors = []

    def produce():
        try:
            for k in range(n_packets):
                fr = [f for f in frames_in if k * per_packet <= f.exposure_end_us < (k + 1) * per_packet]
                ring.push(Packet(events=ev[k * per_packet:(k + 1) * per_packet], frames=fr), timeout_s=10)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)
        finally:
            ring.close()

    got, frames_out = [], []
    producer = threading.Thread(target=produce)
    producer.start()
    while not ring.exhausted:
        entry = ring.peek_frame()
        chunk = ring.read_events(333, until_index=entry.end_index if entry else None)
        got.append(chunk.events)
        if entry is not None and ring.read_index >= entry.end_index:
            frames_out.append(ring.pop_frame())
        if len(chunk.events) == 0 and entry is None:
            ring.wait(ring.version, 0.05)
    producer.join(timeout=10)
    assert not errors and not producer.is_alive()
    got = concat(got)
    assert np.all(np.diff(got["t"]) > 0), "order kept, nothing duplicated"
    assert np.all(np.isin(got["t"], t)), "nothing invented"
    if policy == "wait":
        np.testing.assert_array_equal(got, ev)
        assert [e.frame for e in frames_out] == frames_in
    else:
        assert len(got) + ring.dropped_events == len(ev)
        assert len(frames_out) + ring.dropped_frames == len(frames_in)


def test_packed_event_arrays_are_accepted(rng):
    # np.concatenate of EVENT_DTYPE arrays yields a packed 13-byte dtype; the ring must store it correctly
    ev = events_at_random_pixels(np.arange(20), rng)
    packed = np.concatenate([ev[:10], ev[10:]])
    assert packed.dtype.itemsize != EVENT_DTYPE.itemsize
    ring = EventRing(capacity_events=64, policy="wait")
    ring.push(Packet(events=packed))
    np.testing.assert_array_equal(drain(ring), ev)


def test_a_read_through_a_late_window_reaches_a_frame_queued_after_it_in_one_read():
    """An APS frame queued after events later than its late window (a live DAVIS sends it after the readout):
    reading through the window must still take the frame's events in one read, not one event per read."""
    rng = np.random.default_rng(0)
    ring = EventRing(capacity_events=1 << 12, policy="wait")
    ring.push(Packet(events=events_at_random_pixels(np.arange(0, 100), rng), watermark_us=99))
    ring.push(Packet(frames=[frame(0, 20)], watermark_us=100))  # queued at index 100, its exposure ended at 20
    entry = ring.peek_frame()
    reads = 0
    while ring.read_index < entry.end_index:  # the worker's quiet path with a 10 µs clock offset
        ring.read_events(1 << 16, None, entry.frame.exposure_end_us + 10)
        reads += 1
    assert reads == 1, f"{reads} reads to reach the frame"


def test_a_stop_ends_the_rings_page_touching_between_chunks_and_the_ring_still_works(monkeypatch, rng):
    """The ring writes its memory at start-up (page faults before data flows); a large --ring-events (16 GiB) took
    13 s in that one numpy call, through which Ctrl-C or SIGTERM waited. The stop is now asked between chunks,
    and whatever was not written yet still reads as zeros."""
    from edi_live import ring_buffer

    monkeypatch.setattr(ring_buffer, "_PREFAULT_ROWS", 64)
    asked: list[int] = []

    def stop_after_two() -> bool:
        asked.append(1)
        return len(asked) > 2

    ring = EventRing(64 * 10, 4, stop=stop_after_two)
    assert len(asked) == 3  # two chunks written, the third ask stopped it (not one ask per chunk, ten)
    every = []
    ring_full = EventRing(64 * 10, 4, stop=lambda: every.append(1) or False)
    assert len(every) == 10
    for r in (ring, ring_full):
        ev = events_at_random_pixels(np.arange(100, dtype=np.int64), rng)
        assert r.push(Packet(events=ev, frames=[], watermark_us=100))
        assert np.array_equal(r.read_events(1000).events, ev)
        assert not r._store._buf[100:].any()  # the rest: zeros, written or not
