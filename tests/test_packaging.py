"""The installed package is the whole package: a wheel built from this tree holds every module of edi_live and
drivers, and the udev rule. (An explicit package list once left edi_live.simulation out, so a `pip install .` or
the Docker image could not start the emulated camera; the editable install the tests run on never showed it.)
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("edi_live", "drivers")


def _sources() -> list[str]:
    """Every file of the packages the wheel must carry, relative to the repository root."""
    out = []
    for package in PACKAGES:
        for path in (REPO / package).rglob("*"):
            if path.is_file() and "__pycache__" not in path.parts and path.suffix in (".py", ".rules"):
                out.append(path.relative_to(REPO).as_posix())
    return sorted(out)


def test_a_wheel_built_from_the_tree_holds_every_module_and_the_udev_rule(tmp_path):
    tree = tmp_path / "tree"
    tree.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, tree / name)
    for package in PACKAGES:
        shutil.copytree(REPO / package, tree / package, ignore=shutil.ignore_patterns("__pycache__"))
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", ".", "-w", "out"],
                          cwd=tree, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    wheels = list((tree / "out").glob("edi_live-*.whl"))
    assert len(wheels) == 1, wheels
    held = set(zipfile.ZipFile(wheels[0]).namelist())
    sources = _sources()
    assert "edi_live/simulation/engine.py" in sources and "drivers/99-edi-live-davis.rules" in sources
    missing = [name for name in sources if name not in held]
    assert not missing, f"the wheel lacks {missing}"
