"""Shared fixtures: a seeded rng, the three real DAVIS346 recordings, and the repository root. Every test (and
every node it starts) keeps live-camera calibrations in a temporary folder, never in the user's home.

The real recordings live in ../shared/data/real/ beside the checkout (never copied into the repository).
They are always there for developers and CI, so a missing file is a failure, not a skip.
"""

from __future__ import annotations

import os
import tempfile
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


@pytest.fixture(autouse=True, scope="session")
def _calibrations_in_a_temporary_folder():
    """A live (or emulated) camera loads and saves its calibration under $XDG_CONFIG_HOME: isolate it."""
    before = os.environ.get("XDG_CONFIG_HOME")
    with tempfile.TemporaryDirectory(prefix="edi-live-tests-config-") as folder:
        os.environ["XDG_CONFIG_HOME"] = folder
        yield
    if before is None:
        os.environ.pop("XDG_CONFIG_HOME", None)
    else:
        os.environ["XDG_CONFIG_HOME"] = before


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
