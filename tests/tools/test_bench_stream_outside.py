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
