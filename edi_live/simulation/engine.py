"""The simulation run: steps the scene over the render grid and produces events, blurred APS frames and sharp
ground truth that all agree with one scene definition. Owns `simulate()` and its result, `Simulation`.

- Events: ESIM's rule (events.py): each pixel keeps a reference log level; every crossing of ref +/- its own
  threshold emits one event with a linearly interpolated timestamp. Events without scene information are
  added after the signal events (they do not move the reference level).
- APS frames: the exact time average of the linear intensity exp(log I(t)) over the exposure window
  (closed form per grid segment), scaled to 0..255, then the camera model (camera.py) makes 8-bit values.
- Ground truth: exp(log I(t)) at mid-exposure of every frame and at latent times between frames, float32
  on the same 0..255 linear scale as the APS frames (not quantised).

Deterministic for a config (seed included). Effects added later draw from their own random streams, so a
config without them gives the same output as before they existed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from edi_live.checks import available_memory_bytes
from edi_live.datatypes import IMU_DTYPE, Frame
from edi_live.simulation import camera, colour_scene, events
from edi_live.simulation.config import SceneConfig, check_memory, validate
from edi_live.simulation.motion import Renderer, choose_step_us

# seeds of the random streams of later effects: numpy.random.default_rng([seed, STREAM])
_JITTER_STREAM, _SHOT_STREAM = 101, 102


@dataclass
class Simulation:
    """Result of `simulate()`. Event times and frame windows are absolute µs (t0_us + offset)."""

    config: SceneConfig
    events: np.ndarray  # EVENT_DTYPE, time-ordered, signal + noise
    is_noise: np.ndarray  # bool per event: background, shot-noise or hot-pixel event
    frames: list[Frame]  # APS frames (uint8), exposure windows on the grid
    aps_linear: np.ndarray  # (n_frames, H, W) float32: exact exposure means on 0..255, before the camera model
    gt_t_us: np.ndarray  # (n_gt,) int64 ground-truth times
    gt_images: np.ndarray  # (n_gt, H, W) float32 sharp linear intensity on 0..255; (n_gt, H, W, 3) BGR in colour
    gt_kind: np.ndarray  # (n_gt,) int8: 0 = mid-exposure of frame gt_frame[i], 1 = latent after it, 2 = extra
    gt_frame: np.ndarray  # (n_gt,) int32: index of the APS frame whose mid-exposure precedes (or is) t; -1 none
    c_on_map: np.ndarray  # (H, W) float32 per-pixel ON thresholds actually used
    c_off_map: np.ndarray
    hot_pixel_xy: np.ndarray  # (n_hot, 2) int
    step_us: int
    imu: np.ndarray = field(default_factory=lambda: np.zeros(0, IMU_DTYPE))
    wall_s: float = 0.0
    lamp_mask: np.ndarray | None = None  # (H, W) float32 weight of the flickering lamp at t0, None without one

    @property
    def mid_exposure_us(self) -> np.ndarray:
        return np.array([(f.exposure_start_us + f.exposure_end_us) // 2 for f in self.frames], np.int64)

    def gt_at(self, t_us: int) -> np.ndarray:
        i = int(np.flatnonzero(self.gt_t_us == t_us)[0])
        return self.gt_images[i]

    def camera(self) -> dict:
        """The true camera parameters (see camera.true_camera)."""
        return camera.true_camera(self.config, self.c_on_map, self.c_off_map, self.hot_pixel_xy)


def _gt_schedule(cfg: SceneConfig, mids: np.ndarray, duration_us: int):
    """Ground-truth times (sorted), kinds and frame indices: each mid-exposure, latent times after it, extras."""
    gt_t, gt_kind, gt_frame = [], [], []
    for i, m in enumerate(mids):
        gt_t.append(m), gt_kind.append(0), gt_frame.append(i)
        if i + 1 < len(mids):
            for j in range(1, cfg.latent_per_interval + 1):
                gt_t.append(m + (mids[i + 1] - m) * j // (cfg.latent_per_interval + 1))
                gt_kind.append(1), gt_frame.append(i)
    for t in cfg.gt_extra_us:
        if not 0 <= t <= duration_us:
            raise ValueError(f"ground-truth time {t} µs is outside the simulated 0..{duration_us} µs")
        gt_t.append(int(t)), gt_kind.append(2), gt_frame.append(int(np.searchsorted(mids, t, side="right")) - 1)
    if not cfg.ground_truth:
        gt_t, gt_kind, gt_frame = [], [], []
    order = np.argsort(np.array(gt_t, np.int64), kind="stable")
    return (np.array(gt_t, np.int64)[order], np.array([gt_kind[i] for i in order], np.int8),
            np.array([gt_frame[i] for i in order], np.int32))


def segment_mean(e0: np.ndarray, l0: np.ndarray, l1: np.ndarray) -> np.ndarray:
    """Exact mean of exp(log-linear l0 -> l1) over one segment, given e0 = exp(l0)."""
    dl = l1 - l0
    ratio = np.ones_like(dl)
    np.divide(np.expm1(dl), dl, out=ratio, where=np.abs(dl) > 1e-6)
    return e0 * ratio


def simulate(cfg: SceneConfig) -> Simulation:
    """Run the simulator. Deterministic for a given config (seed included)."""
    wall0 = time.perf_counter()
    validate(cfg)
    rng = np.random.default_rng(cfg.seed + 1)
    w, h = cfg.width, cfg.height
    renderer = Renderer(cfg)
    step_us = choose_step_us(cfg, renderer.max_speed_px_s())
    duration_us = int(round(cfg.duration_s * 1e6))
    n_steps = duration_us // step_us
    duration_us = n_steps * step_us
    con, coff = camera.threshold_maps(cfg, rng)
    if renderer.channels is not None and tuple(cfg.color_c_scale) != (1.0, 1.0, 1.0):
        con, coff = colour_scene.scale_thresholds(con, coff, renderer.channels, cfg.color_c_scale)

    # APS exposure windows (relative µs) fully inside the simulated time
    starts = np.arange(cfg.first_exposure_us, duration_us - cfg.exposure_us + 1, cfg.frame_interval_us, dtype=np.int64)
    ends = starts + cfg.exposure_us
    n_gt = (starts.size * (cfg.latent_per_interval + 1) + len(cfg.gt_extra_us)) if cfg.ground_truth else 0
    check_memory(cfg, starts.size, n_gt, 1 if renderer.channels is None else 3, available_memory_bytes())
    gt_t, gt_kind, gt_frame = _gt_schedule(cfg, (starts + ends) // 2, duration_us)
    gt_images = np.zeros((gt_t.size, h, w) + (() if renderer.channels is None else (3,)), np.float32)
    aps_linear = np.zeros((starts.size, h, w), np.float32)
    aps_acc: dict[int, np.ndarray] = {}  # only the exposures open right now (float64 accumulators)
    n_seg = cfg.exposure_us // step_us

    l0 = renderer.log_frame(0.0).ravel()
    ref = l0.copy()
    if cfg.ref_jitter > 0:  # a real pixel's reference was set by its last event, long before the start
        jitter = np.random.default_rng([cfg.seed, _JITTER_STREAM]).uniform(-1.0, 1.0, ref.size)
        ref = ref + jitter * cfg.ref_jitter * np.minimum(con, coff)
    shot_rng = np.random.default_rng([cfg.seed, _SHOT_STREAM])
    e0 = np.exp(l0)
    last_t = np.full(w * h, -np.inf)
    chunks_pix, chunks_t, chunks_pol = [], [], []
    shot_pix, shot_t, shot_pol = [], [], []
    gt_pos = 0
    for k in range(n_steps):
        ta, tb = k * step_us, (k + 1) * step_us
        l1 = renderer.log_frame(tb * 1e-6).ravel()
        pix, t_s, pol = events.signal_events(ref, l0, l1, con, coff, ta * 1e-6, step_us * 1e-6,
                                             cfg.refractory_us * 1e-6, last_t)
        if pix.size:
            chunks_pix.append(pix), chunks_t.append(t_s), chunks_pol.append(pol)
        if cfg.shot_noise_hz > 0:
            sp, st, so = events.shot_noise_events(cfg, shot_rng, l0, ta * 1e-6, step_us * 1e-6)
            shot_pix.append(sp), shot_t.append(st), shot_pol.append(so)
        # exact mean of exp(log-linear) over this segment, added to every exposure that contains it
        active = np.flatnonzero((starts <= ta) & (ends >= tb))
        e1 = np.exp(l1)
        if active.size:
            seg = segment_mean(e0, l0, l1)
            for a in active:
                if a in aps_acc:
                    aps_acc[a] += seg
                else:
                    aps_acc[a] = seg.astype(np.float64)
        for a in np.flatnonzero(ends == tb):
            aps_linear[a] = (255.0 * aps_acc.pop(int(a)) / n_seg).reshape(h, w)
        while gt_pos < gt_t.size and gt_t[gt_pos] <= tb:  # sorted, so each is rendered in its segment
            a = (gt_t[gt_pos] - ta) / step_us
            if renderer.channels is None:
                gt_images[gt_pos] = (255.0 * np.exp(l0 + a * (l1 - l0))).reshape(h, w)
            else:  # every channel, log-linear between the same grid samples as the mosaic
                la, lb = renderer.log_frame_bgr(ta * 1e-6), renderer.log_frame_bgr(tb * 1e-6)
                gt_images[gt_pos] = 255.0 * np.exp(la + a * (lb - la))
            gt_pos += 1
        l0, e0 = l1, e1

    sig_pix = np.concatenate(chunks_pix) if chunks_pix else np.zeros(0, np.int64)
    sig_t = np.concatenate(chunks_t) if chunks_t else np.zeros(0)
    sig_pol = np.concatenate(chunks_pol) if chunks_pol else np.zeros(0, bool)
    nz_pix, nz_t, nz_pol, hot_xy = events.noise_events(cfg, rng, duration_us * 1e-6)
    nz_pix, nz_t, nz_pol = (np.concatenate([a, *b]) for a, b in ((nz_pix, shot_pix), (nz_t, shot_t),
                                                                  (nz_pol, shot_pol)))
    pix = np.concatenate([sig_pix, nz_pix])
    t_us = np.rint(np.concatenate([sig_t, nz_t]) * 1e6).astype(np.int64)
    pol = np.concatenate([sig_pol, nz_pol])
    is_noise = np.concatenate([np.zeros(sig_pix.size, bool), np.ones(nz_pix.size, bool)])
    order = np.argsort(t_us, kind="stable")
    evs = events.to_events(pix[order], t_us[order] + cfg.t0_us + cfg.event_offset_us, pol[order], w)
    is_noise = is_noise[order]

    frames = [Frame(image=camera.aps_values(cfg, aps_linear[i], rng), exposure_start_us=int(starts[i] + cfg.t0_us),
                    exposure_end_us=int(ends[i] + cfg.t0_us), start_us=int(starts[i] + cfg.t0_us),
                    end_us=int(ends[i] + cfg.t0_us), seq=i, color_filter=cfg.color_filter)
              for i in range(starts.size)]
    imu = imu_samples(cfg, duration_us) if cfg.imu else np.zeros(0, IMU_DTYPE)
    return Simulation(config=cfg, events=evs, is_noise=is_noise, frames=frames, aps_linear=aps_linear,
                      gt_t_us=gt_t + cfg.t0_us, gt_images=gt_images, gt_kind=gt_kind, gt_frame=gt_frame,
                      c_on_map=con.reshape(h, w), c_off_map=coff.reshape(h, w), hot_pixel_xy=hot_xy,
                      step_us=step_us, imu=imu, wall_s=time.perf_counter() - wall0,
                      lamp_mask=renderer.lamp_image(0.0))


def imu_samples(cfg: SceneConfig, duration_us: int, rate_hz: float = 200.0) -> np.ndarray:
    """Gyro z = the scene's rotation rate, accelerometer = gravity; enough for a stream that exists."""
    t = np.arange(0, duration_us, int(1e6 / rate_hz), dtype=np.int64)
    imu = np.zeros(t.size, IMU_DTYPE)
    imu["t"] = t + cfg.t0_us
    imu["temperature_c"] = 30.0
    imu["accel_g"][:, 1] = -1.0
    imu["gyro_dps"][:, 2] = cfg.rotation_deg_s
    return imu
