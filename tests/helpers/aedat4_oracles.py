"""Independent readers for AEDAT4 tests: dv-processing and the `aedat` package, returning plain numpy/dicts.

Our reader is checked against these, never against its own output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def dv_read(path: Path) -> dict:
    """Everything dv-processing's MonoCameraRecording gives: events, frames (SOE, exposure, image), IMU, triggers."""
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(str(path))
    out = {"camera": rec.getCameraName(), "resolution": rec.getEventResolution(), "time_range": rec.getTimeRange()}
    events = []
    if rec.isEventStreamAvailable():
        while (batch := rec.getNextEventBatch()) is not None:
            events.append(batch.numpy().copy())
    out["events"] = np.concatenate(events) if events else None
    frames = []
    if rec.isFrameStreamAvailable():
        while (f := rec.getNextFrame()) is not None:
            frames.append({"t": f.timestamp, "exposure_us": int(f.exposure.total_seconds() * 1e6 + 0.5),
                           "image": f.image.copy(), "source": int(f.source)})
    out["frames"] = frames
    imu = []
    if rec.isImuStreamAvailable():
        while (batch := rec.getNextImuBatch()) is not None:
            imu += [(s.timestamp, s.temperature, s.accelerometerX, s.accelerometerY, s.accelerometerZ,
                     s.gyroscopeX, s.gyroscopeY, s.gyroscopeZ, s.magnetometerX, s.magnetometerY, s.magnetometerZ)
                    for s in batch]
    out["imu"] = np.array(imu, dtype=np.float64).reshape(-1, 11)
    trig = []
    if rec.isTriggerStreamAvailable():
        while (batch := rec.getNextTriggerBatch()) is not None:
            trig += [(t.timestamp, int(t.type)) for t in batch]
    out["triggers"] = np.array(trig, dtype=np.int64).reshape(-1, 2)
    return out


def aedat_read(path: Path) -> dict:
    """Everything the `aedat` package (Rust) gives, per stream type, in file order."""
    import aedat

    dec = aedat.Decoder(str(path))
    out = {"streams": dec.id_to_stream(), "events": [], "frames": [], "imus": [], "triggers": []}
    for packet in dec:
        if "events" in packet:
            out["events"].append(packet["events"])
        elif "frame" in packet:
            out["frames"].append(packet["frame"])
        elif "imus" in packet:
            out["imus"].append(packet["imus"])
        elif "triggers" in packet:
            out["triggers"].append(packet["triggers"])
    for key in ("events", "imus", "triggers"):
        out[key] = np.concatenate(out[key]) if out[key] else None
    return out
