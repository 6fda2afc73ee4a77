"""An endless simulated scene as time-ordered `Packet`s, for the USB emulator when no recording is given.

The same scene, event and camera models as `simulate()`, stepped for ever: a textured scene oscillating
slowly (so it never runs off its canvas), 10 ms packets, APS frames whose exposure and interval are read
before each frame (an emulator follows its APS registers), 1 kHz IMU. Deterministic for a seed and epoch.
"""

from __future__ import annotations

import time
from typing import Iterator

import numpy as np

from edi_live.datatypes import IMU_DTYPE, Frame, Packet
from edi_live.simulation import camera, events
from edi_live.simulation.config import SceneConfig
from edi_live.simulation.engine import segment_mean
from edi_live.simulation.motion import Renderer

STEP_US = 2000  # render grid: the scene moves at most ~0.2 px per step
PACKET_US = 10_000


def stream_config(width: int, height: int, seed: int, color_filter: str | None = None) -> SceneConfig:
    """The emulator's scene: blocks drifting back and forth at up to ~85 px/s, a DAVIS-like c of 0.2; coloured
    blocks seen through a Bayer mosaic when `color_filter` names one (e.g. "RGGB", a colour DAVIS346)."""
    return SceneConfig(width=width, height=height, texture="blocks", seed=seed, velocity_px_s=(80.0, 25.0),
                       oscillation_period_s=4.0, duration_s=4.0, c_on=0.2, c_off=0.2, noise_rate_hz=0.1,
                       color_filter=color_filter)


class _Exposure:
    """One APS exposure being integrated over [start, end) µs (relative to the epoch)."""

    def __init__(self, start: int, end: int, n_px: int):
        self.start, self.end = start, end
        self.acc = np.zeros(n_px, np.float64)

    def add(self, seg: np.ndarray, ta: int, tb: int) -> None:
        overlap = min(tb, self.end) - max(ta, self.start)
        if overlap > 0:  # segment means are exact; a partial overlap takes its share of the segment's mean
            self.acc += seg * overlap


def generated_scene(width: int = 240, height: int = 180, *, epoch_us: int | None = None, seed: int = 7,
                    timing: dict[str, int] | None = None, color_filter: str | None = None) -> Iterator[Packet]:
    """Endless packets of the simulated scene. `timing` ({"exposure_us", "interval_us"}, read before each
    frame) defaults to libcaer's 4 ms every 40 ms. `color_filter`: a colour sensor's Bayer pattern (frames are
    raw mosaics carrying it), None for a grey one."""
    cfg = stream_config(width, height, seed, color_filter)
    rng = np.random.default_rng(seed + 1)
    t0 = time.time_ns() // 1000 if epoch_us is None else epoch_us
    timing = timing if timing is not None else {"exposure_us": 4000, "interval_us": 40000}
    renderer = Renderer(cfg)
    con, coff = camera.threshold_maps(cfg, rng)
    n_px = width * height
    l0 = renderer.log_frame(0.0).ravel()
    ref, e0 = l0.copy(), np.exp(l0)
    last_t = np.full(n_px, -np.inf)
    open_exp: list[_Exposure] = []
    pending: list[Frame] = []
    next_frame_us, seq, now = 0, 0, 0
    while True:
        pix_l, t_l, pol_l = [], [], []
        for _ in range(PACKET_US // STEP_US):
            ta, tb = now, now + STEP_US
            while next_frame_us < tb:  # exposures starting in this step
                exposure = max(1, int(timing["exposure_us"]))
                open_exp.append(_Exposure(next_frame_us, next_frame_us + exposure, n_px))
                next_frame_us += max(int(timing["interval_us"]), exposure + 1000)
            l1 = renderer.log_frame(tb * 1e-6).ravel()
            pix, t_s, pol = events.signal_events(ref, l0, l1, con, coff, ta * 1e-6, STEP_US * 1e-6, 0.0, last_t)
            pix_l.append(pix), t_l.append(t_s), pol_l.append(pol)
            seg = segment_mean(e0, l0, l1)
            for ex in open_exp:
                ex.add(seg, ta, tb)
            for ex in [ex for ex in open_exp if ex.end <= tb]:
                open_exp.remove(ex)
                linear = (255.0 * ex.acc / (ex.end - ex.start)).reshape(height, width)
                start = t0 + ex.start
                pending.append(Frame(camera.aps_values(cfg, linear, rng), start, start + ex.end - ex.start,
                                     start, start + ex.end - ex.start, seq, color_filter=color_filter))
                seq += 1
            l0, e0 = l1, np.exp(l1)
            now = tb
        lo = now - PACKET_US
        nz_n = rng.poisson(cfg.noise_rate_hz * n_px * PACKET_US * 1e-6)
        pix_l.append(rng.integers(0, n_px, nz_n)), t_l.append((lo + rng.random(nz_n) * PACKET_US) * 1e-6)
        pol_l.append(rng.random(nz_n) < 0.5)
        pix, t_s, pol = np.concatenate(pix_l), np.concatenate(t_l), np.concatenate(pol_l)
        t_us = np.rint(t_s * 1e6).astype(np.int64)
        order = np.argsort(t_us, kind="stable")
        evs = events.to_events(pix[order], t_us[order] + t0, pol[order], width)
        # a frame goes out with the packet that holds the end of its exposure (after the events up to it)
        frames = [f for f in pending if f.exposure_end_us < t0 + now]
        pending = [f for f in pending if f.exposure_end_us >= t0 + now]
        imu = np.zeros(PACKET_US // 1000, IMU_DTYPE)
        imu["t"] = t0 + lo + np.arange(PACKET_US // 1000) * 1000 + 500
        imu["temperature_c"] = 30.0
        imu["accel_g"] = (0.0, -1.0, 0.0)
        yield Packet(events=evs, frames=frames, imu=imu, watermark_us=t0 + now)
