"""Shared builders for the tests: random recordings as in-memory Packets (the oracle), random events at given times,
collectors."""

from __future__ import annotations

import numpy as np

from edi_live.datatypes import EVENT_DTYPE, IMU_DTYPE, Frame, Packet


def events_at_random_pixels(t_us: np.ndarray, rng: np.random.Generator, width: int = 240,
                            height: int = 180) -> np.ndarray:
    """Events at the given times (EVENT_DTYPE), each at a random pixel with a random polarity."""
    ev = np.zeros(len(t_us), EVENT_DTYPE)
    ev["t"] = t_us
    ev["x"] = rng.integers(0, width, len(t_us))
    ev["y"] = rng.integers(0, height, len(t_us))
    ev["p"] = rng.integers(0, 2, len(t_us)).astype(bool)
    return ev


def random_recording(rng: np.random.Generator, width: int, height: int, *, n_events: int = 20000,
                     duration_us: int = 300_000, t0_us: int = 1_700_000_000_000_000, n_frames: int = 3,
                     n_imu: int = 20, even_pixels: bool = False) -> list[Packet]:
    """Time-ordered packets obeying the Packet ordering contract: random events (with long quiet stretches so
    several timestamp wraps happen), frames after the events up to their exposure end, IMU samples."""
    t = np.sort(rng.integers(0, duration_us, n_events)) + t0_us
    t[n_events // 2:] += 200_000  # a 200 ms silence: several wraps with no timestamp in between
    ev = np.zeros(n_events, EVENT_DTYPE)
    ev["t"], ev["x"], ev["y"], ev["p"] = t, rng.integers(0, width, n_events), rng.integers(0, height, n_events), \
        rng.random(n_events) < 0.5
    end = int(t[-1])
    frames = []
    for k in range(n_frames):
        es = t0_us + 20_000 + k * (end - t0_us - 40_000) // max(n_frames, 1)
        img = rng.integers(0, 256, (height, width)).astype(np.uint8)
        if even_pixels:
            img &= 0xFE
        frames.append(Frame(img, int(es), int(es) + 4000 + 1000 * k, seq=k))
    imu = np.zeros(n_imu, IMU_DTYPE)
    imu["t"] = np.sort(rng.integers(t0_us, end, n_imu))
    imu["accel_g"] = rng.uniform(-3.9, 3.9, (n_imu, 3))
    imu["gyro_dps"] = rng.uniform(-490, 490, (n_imu, 3))
    imu["temperature_c"] = rng.uniform(20, 40, n_imu)
    # one packet per 10 ms, frames placed after their exposure end
    packets = []
    edges = list(range(t0_us, end + 10_000, 10_000))
    for lo, hi in zip(edges[:-1], edges[1:]):
        e = ev[(ev["t"] >= lo) & (ev["t"] < hi)]
        fr = [f for f in frames if lo <= f.exposure_end_us < hi]
        im = imu[(imu["t"] >= lo) & (imu["t"] < hi)]
        packets.append(Packet(events=e, frames=fr, imu=im, watermark_us=hi))
    return packets


def flatten(packets):
    ps = [p for p in packets if p is not None]
    events = np.concatenate([p.events for p in ps]) if ps else np.zeros(0, EVENT_DTYPE)
    frames = [f for p in ps for f in p.frames]
    imu = np.concatenate([p.imu for p in ps]) if ps else np.zeros(0, IMU_DTYPE)
    return events, frames, imu



def packets_by_frame(events: np.ndarray, frames: list[Frame], tail: bool = True) -> list[Packet]:
    """One Packet per APS frame, holding the events up to its exposure end (as a camera delivers them), then the
    events after the last frame in one more Packet (`tail`); `events` sorted by t."""
    packets, cut = [], 0
    for f in frames:
        end = int(np.searchsorted(events["t"], f.exposure_end_us, side="right"))
        packets.append(Packet(events=events[cut:end], frames=[f]))
        cut = end
    if tail:
        packets.append(Packet(events=events[cut:]))
    return packets
