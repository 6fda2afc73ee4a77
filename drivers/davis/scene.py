"""A synthetic scene for the emulator when no recording is given: a bright bar sweeping over a dark
background, with APS frames and IMU samples, as time-ordered `Packet`s."""

from __future__ import annotations

import time
from typing import Iterator

import numpy as np

from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, Frame, Packet


def generated_scene(width: int = 240, height: int = 180, *, epoch_us: int | None = None,
                    seed: int = 7) -> Iterator[Packet]:
    """An endless synthetic scene: a bright bar sweeping right over a dark background, 10 ms packets, APS
    frames every 40 ms (4 ms exposure), 1 kHz IMU. Deterministic for a given seed and epoch."""
    rng = np.random.default_rng(seed)
    t0 = time.time_ns() // 1000 if epoch_us is None else epoch_us
    bar_w, speed_px_per_ms = max(4, width // 12), 0.25
    step_ms = 10
    k = 0
    while True:
        t_start = t0 + k * step_ms * 1000
        evs = []
        for ms in range(step_ms):
            now = k * step_ms + ms
            for edge, pol in ((now * speed_px_per_ms, True), (now * speed_px_per_ms - bar_w, False)):
                c0, c1 = int(edge) % width, int(edge + speed_px_per_ms) % width
                if c0 == c1:
                    continue
                ys = np.arange(height // 4, 3 * height // 4)
                ev = np.zeros(len(ys), dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "?")])
                ev["t"] = t0 + now * 1000 + rng.integers(0, 1000, len(ys))
                ev["x"], ev["y"], ev["p"] = c1, ys, pol
                evs.append(ev)
        events = np.zeros(sum(len(e) for e in evs), EVENT_DTYPE)
        if evs:
            allev = np.concatenate(evs)
            allev = allev[np.argsort(allev["t"], kind="stable")]
            for name in ("t", "x", "y", "p"):
                events[name] = allev[name]
        frames = []
        if (k * step_ms) % 40 == 0:
            img = np.full((height, width), 40, np.uint8)
            pos = int(k * step_ms * speed_px_per_ms)
            cols = (np.arange(pos - bar_w, pos) % width)
            img[height // 4: 3 * height // 4, cols] = 200
            frames.append(Frame(img, t_start, t_start + 4000, t_start, t_start + 4000, k // 4))
        imu = np.zeros(step_ms, IMU_DTYPE)
        imu["t"] = t_start + np.arange(step_ms) * 1000 + 500
        imu["temperature_c"] = 30.0
        imu["accel_g"] = (0.0, -1.0, 0.0)
        k += 1
        # frames after the events up to their exposure end: exposure ends within this 10 ms packet
        yield Packet(events=events, frames=frames, imu=imu, watermark_us=t_start + step_ms * 1000)
