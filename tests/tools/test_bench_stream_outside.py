"""tools.bench_stream's latency (tools/stream_latency.py) seen from the subscriber: receive time against the paced
wall time of each frame's last event, relative to the fastest frame of each pass over a looped recording."""

import numpy as np

from tools.stream_latency import outside_latency_us


def test_latency_relative_to_the_fastest_frame_of_each_pass():
    speed = 0.5  # sensor µs -> wall µs: x2
    t = np.array([1_000, 2_000, 3_000, 1_000_400, 100, 1_100], np.int64)  # the second pass starts at t = 100
    delay_us = np.array([300, 100, 700, 250, 50, 450])
    start_us = np.array([0, 0, 0, 0, 5_000_000, 5_000_000])  # the loop restarts the replay clock
    recv_ns = (start_us + t / speed + delay_us) * 1000
    got = outside_latency_us(np.stack([recv_ns.astype(np.int64), t, np.zeros(6, np.int64)], axis=1), speed)
    assert np.allclose(got, [200, 0, 600, 150, 0, 400])


def _arrivals(recv_us: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.stack([(recv_us * 1000).astype(np.int64), t, np.zeros(t.size, np.int64)], axis=1)


def test_a_stall_the_pacer_restarts_its_schedule_after_counts_once_not_in_every_later_frame():
    """Stopped for 3 s (Ctrl-Z, a stalled machine), the paced replay goes on from there at its speed
    (drivers.pacing): the frames after the stall are late against the old schedule only by the stall."""
    t = np.arange(1_000, 11_000, 1_000, dtype=np.int64)
    delay_us = np.array([200, 100, 300, 100, 150, 400, 100, 250, 100, 300])
    stall_us = np.where(np.arange(10) >= 5, 3_000_000, 0)  # from the sixth frame on, a new schedule
    got = outside_latency_us(_arrivals(t + delay_us + stall_us, t), 1.0)
    assert np.allclose(got, [100, 0, 200, 0, 50, 300, 0, 150, 0, 200])


def test_a_late_frame_under_the_pacers_limit_stays_late():
    t = np.arange(1_000, 6_000, 1_000, dtype=np.int64)
    delay_us = np.array([100, 900_000, 100, 100, 100])  # 0.9 s late once: the pacer catches up, it is latency
    got = outside_latency_us(_arrivals(t + delay_us, t), 1.0)
    assert np.allclose(got, [0, 899_900, 0, 0, 0])


def test_a_clock_jump_the_pacer_skips_starts_a_new_schedule():
    t = np.array([1_000, 2_000, 3_000 + 100_000_000, 4_000 + 100_000_000], np.int64)  # 100 s ahead: skipped
    recv_us = np.array([1_100, 2_000, 3_300, 4_000])  # replayed without waiting for the jump
    got = outside_latency_us(_arrivals(recv_us, t), 1.0)
    assert np.allclose(got, [100, 0, 300, 0])
