"""Shared fixtures: a seeded rng, the three real DAVIS346 recordings, and the repository root.

The real recordings live in ../shared/data/real/ beside the checkout (never copied into the repository).
They are always there for developers and CI, so a missing file is a failure, not a skip.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
REAL_DATA_DIR = REPO_ROOT.parent / "shared" / "data" / "real"
REAL_RECORDING_NAMES = (
    "emlb_demo-01_davis346.aedat4",  # motion blur, newest DV frame layout, 13 frames
    "aestream_davis346.aedat4",  # older DV layout (timestamp = mid-exposure), camera motion
    "evlib_sample_davis346.aedat4",  # tiny, FileDataTable without timestamps
)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20190616)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def real_recordings() -> dict[str, Path]:
    paths = {name: REAL_DATA_DIR / name for name in REAL_RECORDING_NAMES}
    missing = [str(p) for p in paths.values() if not p.is_file()]
    if missing:
        pytest.fail(f"real recordings missing (expected beside the checkout): {missing}")
    return paths
