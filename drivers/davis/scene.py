"""A synthetic scene for the emulator when no recording is given: a bright bar sweeping over a dark
background, with APS frames and IMU samples, as time-ordered `Packet`s."""

from __future__ import annotations

import time
from typing import Iterator

import numpy as np

from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, Frame, Packet


def generated_scene(width: int = 240, height: int = 180, *, epoch_us: int | None = None, seed: int = 7,
                    timing: dict[str, int] | None = None) -> Iterator[Packet]:
    """An endless synthetic scene: a bright bar sweeping right over a dark background, 10 ms packets, APS
    frames, 1 kHz IMU. `timing` ({"exposure_us", "interval_us"}, read before each frame, so an emulator can
    follow its APS registers) defaults to libcaer's 4 ms every 40 ms. Deterministic for a seed and epoch."""
    rng = np.random.default_rng(seed)
    t0 = time.time_ns() // 1000 if epoch_us is None else epoch_us
    timing = timing if timing is not None else {"exposure_us": 4000, "interval_us": 40000}
    bar_w, speed_px_per_ms = max(4, width // 12), 0.25
    step_us = 10_000
    next_frame_us, seq, k = 0, 0, 0
    pending: list[Frame] = []
    rows = np.arange(height // 4, 3 * height // 4)
    while True:
        lo = k * step_us
        evs = []
        for ms in range(lo // 1000, (lo + step_us) // 1000):
            for edge, pol in ((ms * speed_px_per_ms, True), (ms * speed_px_per_ms - bar_w, False)):
                c0, c1 = int(edge) % width, int(edge + speed_px_per_ms) % width
                if c0 == c1:
                    continue
                ev = np.zeros(len(rows), EVENT_DTYPE)
                ev["t"] = t0 + ms * 1000 + rng.integers(0, 1000, len(rows))
                ev["x"], ev["y"], ev["p"] = c1, rows, pol
                evs.append(ev)
        events = np.concatenate(evs) if evs else np.zeros(0, EVENT_DTYPE)
        events = events[np.argsort(events["t"], kind="stable")]
        while next_frame_us < lo + step_us:  # frames starting in this step
            exposure = max(1, int(timing["exposure_us"]))
            img = np.full((height, width), 40, np.uint8)
            pos = int((next_frame_us + exposure // 2) / 1000 * speed_px_per_ms)
            img[height // 4: 3 * height // 4, np.arange(pos - bar_w, pos) % width] = 200
            start = t0 + next_frame_us
            pending.append(Frame(img, start, start + exposure, start, start + exposure, seq))
            seq += 1
            next_frame_us += max(int(timing["interval_us"]), exposure + 1000)
        # a frame goes out with the packet that holds the end of its exposure (after the events up to it)
        frames = [f for f in pending if f.exposure_end_us < t0 + lo + step_us]
        pending = [f for f in pending if f.exposure_end_us >= t0 + lo + step_us]
        imu = np.zeros(step_us // 1000, IMU_DTYPE)
        imu["t"] = t0 + lo + np.arange(step_us // 1000) * 1000 + 500
        imu["temperature_c"] = 30.0
        imu["accel_g"] = (0.0, -1.0, 0.0)
        k += 1
        yield Packet(events=events, frames=frames, imu=imu, watermark_us=t0 + lo + step_us)
