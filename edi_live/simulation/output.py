"""Files of a simulation: the recording (AEDAT4 through edi_live's writer) and the ground truth (.npz).

The ground truth holds the sharp frames, their times and kinds, the APS frames before and after the camera
model, and the true camera: the config (every scalar parameter), the per-pixel threshold maps, the hot-pixel
list and, with a flickering lamp, the lamp's mask. Config fields added for the realistic camera are written
only when set, so a file of an ideal camera is byte for byte what it was before they existed.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from edi_live.simulation.camera import true_camera
from edi_live.simulation.config import LATER_FIELDS, SceneConfig
from edi_live.simulation.engine import Simulation

_DEFAULTS = dataclasses.asdict(SceneConfig())


def camera_name(color_filter: str | None) -> str:
    """The camera a simulated recording names: a colour sensor is another camera than a grey one of the same size,
    so that a calibration saved from one is refused for the other (calibrations are keyed by camera and size)."""
    return "edi-live-sim" if color_filter is None else f"edi-live-sim-{color_filter}"


def write_aedat4(sim: Simulation, path: str | Path, *, chunk_events: int = 20_000) -> None:
    """Write events and APS frames (and IMU if simulated) in time order through edi_live's Aedat4Writer.

    Each frame is written after every event up to its exposure end, as a camera would deliver it.
    """
    from edi_live.aedat4.writer import Aedat4Writer

    ev = sim.events
    cfg = sim.config
    with Aedat4Writer(path, cfg.width, cfg.height, events=True, frames=True, imu=bool(sim.imu.size),
                      camera_name=camera_name(cfg.color_filter), color_filter=cfg.color_filter) as wr:
        pos = 0
        imu_pos = 0
        bounds = [f.exposure_end_us for f in sim.frames] + [np.iinfo(np.int64).max]
        for i, bound in enumerate(bounds):
            stop = int(np.searchsorted(ev["t"], bound, side="right"))
            while pos < stop:
                nxt = min(stop, pos + chunk_events)
                wr.write_events(ev[pos:nxt])
                pos = nxt
            if sim.imu.size:
                istop = int(np.searchsorted(sim.imu["t"], bound, side="right"))
                if istop > imu_pos:
                    wr.write_imu(sim.imu[imu_pos:istop])
                    imu_pos = istop
            if i < len(sim.frames):
                wr.write_frame(sim.frames[i])


def config_record(cfg: SceneConfig) -> dict:
    """The config as stored: every field, except later fields that still hold their default."""
    rec = dataclasses.asdict(cfg)
    for k in LATER_FIELDS:
        if rec[k] == _DEFAULTS[k]:
            del rec[k]
    return rec


def save_ground_truth(sim: Simulation, path: str | Path) -> None:
    """Ground truth beside the recording: sharp frames, their times/kinds, the true camera and the config."""
    cfg = config_record(sim.config)
    extra = {} if sim.lamp_mask is None else {"lamp_mask": sim.lamp_mask}
    np.savez_compressed(
        path, gt_t_us=sim.gt_t_us, gt_images=sim.gt_images, gt_kind=sim.gt_kind, gt_frame=sim.gt_frame,
        aps_images=np.stack([f.image for f in sim.frames]) if sim.frames else np.zeros((0, cfg["height"], cfg["width"]), np.uint8),
        aps_linear=sim.aps_linear,
        exposure_start_us=np.array([f.exposure_start_us for f in sim.frames], np.int64),
        exposure_end_us=np.array([f.exposure_end_us for f in sim.frames], np.int64),
        c_on_map=sim.c_on_map, c_off_map=sim.c_off_map, hot_pixel_xy=sim.hot_pixel_xy,
        n_events=np.int64(sim.events.size), n_noise_events=np.int64(sim.is_noise.sum()),
        config_json=json.dumps(cfg), **extra)


def load_ground_truth(path: str | Path) -> dict:
    """Inverse of save_ground_truth: a dict of arrays plus 'config' (dict, every field) and 'camera' (the
    true camera parameters, see camera.true_camera)."""
    with np.load(path) as z:
        out = {k: z[k] for k in z.files}
    stored = json.loads(str(out.pop("config_json")))
    out["config"] = {**_DEFAULTS, **stored}
    fields = {f.name for f in dataclasses.fields(SceneConfig)}
    cfg = SceneConfig(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in out["config"].items()
                         if k in fields})
    out["camera"] = true_camera(cfg, out["c_on_map"], out["c_off_map"], out["hot_pixel_xy"])
    return out
