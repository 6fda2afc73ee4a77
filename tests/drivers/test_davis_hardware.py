"""A real camera, when one is plugged in: `pytest -m hardware tests/drivers/test_davis_hardware.py`
(deselected by default). Checks that the live path produces sane data, not exact values."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.davis.device import DavisSource
from drivers.davis.discovery import list_devices

pytestmark = pytest.mark.hardware


def test_real_camera_streams_events_and_frames():
    if not list_devices():
        pytest.skip("no DAVIS camera attached")
    got, deadline = [], time.monotonic() + 5
    with DavisSource("auto", exposure_us=4000, frame_interval_us=40000) as src:
        for p in src:
            if p is not None:
                got.append(p)
            if time.monotonic() > deadline:
                src.stop()
        w, h = src.info.width, src.info.height
    ev = np.concatenate([p.events for p in got])
    frames = [f for p in got for f in p.frames]
    assert len(ev) and np.all(np.diff(ev["t"]) >= 0) and ev["x"].max() < w and ev["y"].max() < h
    assert frames and all(f.image.shape == (h, w) for f in frames)
