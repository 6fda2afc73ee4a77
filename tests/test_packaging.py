"""The installed package is the whole package: a wheel built from this tree holds every module of edi_live and
drivers, and the udev rule. (An explicit package list once left edi_live.simulation out, so a `pip install .` or
the Docker image could not start the emulated camera; the editable install the tests run on never showed it.)
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

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


def _setuptools_deprecations(output: str) -> set[str]:
    """What setuptools announced as deprecated while building: the summary of each SetuptoolsDeprecationWarning,
    without the build environment's temporary path. (Python's own DeprecationWarnings come from library internals,
    not from a project's configuration.)"""
    return {line.split("SetuptoolsDeprecationWarning:", 1)[1].strip() for line in output.splitlines()
            if "SetuptoolsDeprecationWarning:" in line}


def _ours(built: str, reference: str) -> list[str]:
    """The deprecations announced for our pyproject.toml and not for a minimal one built the same way: an upstream
    notice every project gets (about setuptools itself) is not ours to fix and must not fail the test."""
    return sorted(_setuptools_deprecations(built) - _setuptools_deprecations(reference))


def test_only_deprecations_that_our_pyproject_causes_count():
    config = ("  /tmp/pip-build-env-a/overlay/setuptools/config/_apply_pyprojecttoml.py:82: "
              "SetuptoolsDeprecationWarning: `project.license` as a TOML table is deprecated\n  !!\n"
              "          By 2027-Feb-18, you need to update your project\n  !!\n")
    upstream = ("  /tmp/pip-build-env-{}/overlay/setuptools/_core.py:10: SetuptoolsDeprecationWarning: some internal "
                "hook is deprecated\n  /tmp/pip-build-env-{}/overlay/packaging/x.py:3: DeprecationWarning: a "
                "standard-library call is deprecated\n")
    assert _ours(config + upstream.format("a", "a"), upstream.format("b", "b")) == [
        "`project.license` as a TOML table is deprecated"]
    assert _ours(upstream.format("a", "a"), upstream.format("b", "b")) == []


def _pip_wheel(tree: Path, out: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}  # setuptools' own notices show anyway
    return subprocess.run([sys.executable, "-m", "pip", "wheel", "--verbose", "--no-deps", ".", "-w", str(out)],
                          cwd=tree, env=env, capture_output=True, text=True, timeout=600)


def test_a_wheel_built_from_the_tree_holds_every_module_and_the_udev_rule(tmp_path):
    tree = tmp_path / "tree"
    tree.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, tree / name)
    for package in PACKAGES:
        shutil.copytree(REPO / package, tree / package, ignore=shutil.ignore_patterns("__pycache__"))
    proc = _pip_wheel(tree, tmp_path / "out")
    assert proc.returncode == 0, proc.stderr[-3000:]
    # setuptools announces a date after which a deprecated pyproject.toml no longer builds (the license table did:
    # "By 2027-Feb-18 ... your builds will no longer be supported"); a user's `pip install .` gets the newest one.
    # A minimal project with the same build backend, built the same way, tells its general notices apart.
    reference = tmp_path / "reference"
    (reference / "minimal").mkdir(parents=True)
    (reference / "minimal" / "__init__.py").write_text("")
    backend = re.search(r"^\[build-system\].*?(?=^\[)", (tree / "pyproject.toml").read_text(), re.M | re.S).group(0)
    (reference / "pyproject.toml").write_text(f'{backend}\n[project]\nname = "minimal"\nversion = "1"\n')
    ref = _pip_wheel(reference, tmp_path / "reference-out")
    assert ref.returncode == 0, ref.stderr[-3000:]
    announced = _ours(proc.stdout + proc.stderr, ref.stdout + ref.stderr)
    assert not announced, announced
    wheels = list((tmp_path / "out").glob("edi_live-*.whl"))
    assert len(wheels) == 1, wheels
    held = set(zipfile.ZipFile(wheels[0]).namelist())
    version = re.search(r'^__version__ = "(.+)"$', (REPO / "edi_live" / "__init__.py").read_text(), re.M).group(1)
    assert wheels[0].name.startswith(f"edi_live-{version}-"), (wheels[0].name, version)  # what --version prints
    sources = _sources()
    assert "edi_live/simulation/engine.py" in sources and "drivers/99-edi-live-davis.rules" in sources
    missing = [name for name in sources if name not in held]
    assert not missing, f"the wheel lacks {missing}"


_FIRST_KERNEL = r"""
import os, sys
import numpy as np
import edi_live
from edi_live.aedat4._check import check_events  # a numba kernel with an on-disk cache, defined at import
from edi_live.datatypes import EVENT_DTYPE
ev = np.zeros(3, EVENT_DTYPE)
ev["t"] = [1, 2, 3]
check_events(ev.view(np.uint8), 4, 4, 0)  # compiled now, so its cache files are written
print(edi_live.__file__)
print(os.environ.get("NUMBA_CACHE_DIR", ""))
"""


def _unwritable_install(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """A copy of edi_live whose __pycache__ folders cannot be made (a plain file holds each name, which stops root
    too), run with a home folder that cannot hold ~/.cache: as for a system-wide install used by an account
    without a writable home (a service account, a container's --user)."""
    tree = tmp_path / "site"
    shutil.copytree(REPO / "edi_live", tree / "edi_live", ignore=shutil.ignore_patterns("__pycache__"))
    for package in (tree / "edi_live").rglob("__init__.py"):
        (package.parent / "__pycache__").write_text("not a folder\n")
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, so no folder can be made under it\n")
    (tmp_path / "tmp").mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONPATH")}
    env.update(HOME=str(blocker / "home"), TMPDIR=str(tmp_path / "tmp"), PYTHONPATH=str(tree))
    return tree, env


@pytest.mark.parametrize("numba_first", [False, True], ids=["edi_live-first", "numba-imported-first"])
def test_the_package_imports_and_caches_its_kernels_where_neither_the_package_nor_the_home_is_writable(tmp_path,
                                                                                                       numba_first):
    """numba's cache=True kernels look for a writable folder when they are defined: beside the module, then
    ~/.cache/numba. Where neither can be written, numba raised at import ("cannot cache function ... no locator
    available"), so the node could not even start; edi_live now picks a private folder in the temp directory
    (also when a program imported numba before edi_live, so numba had already read its settings)."""
    tree, env = _unwritable_install(tmp_path)
    script = ("import numba\n" if numba_first else "") + _FIRST_KERNEL
    proc = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    module, cache_dir = proc.stdout.split("\n")[:2]
    assert Path(module).is_relative_to(tree)
    assert Path(cache_dir).is_relative_to(tmp_path / "tmp")
    assert list(Path(cache_dir).rglob("*.nbi")), "no kernel was cached"


def _installed_copy(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    """What an installed user has: edi_live and drivers, and no tools/ (run from another folder)."""
    site = tmp_path / "site"
    for package in PACKAGES:
        shutil.copytree(REPO / package, site / package, ignore=shutil.ignore_patterns("__pycache__"))
    return site, {**os.environ, "PYTHONPATH": str(site)}


def test_every_python_m_command_the_installed_helps_name_runs_without_the_repository_or_says_it_needs_it(tmp_path):
    """`edi-live --help` told an installed user to see the frames with `python -m tools.viewer`, which is not
    installed (the tools run from a repository checkout): No module named 'tools'."""
    site, env = _installed_copy(tmp_path)
    helps = [("edi_live", "--help"), ("edi_live.publisher", "--help"), ("edi_live.client", "--help"),
             ("drivers.udev", "--help")]
    named = {}
    for module, flag in helps:
        proc = subprocess.run([sys.executable, "-m", module, flag], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr[-2000:]
        for line in proc.stdout.splitlines():
            for name in re.findall(r"python -m ([\w.]+)", line):
                if "checkout" not in line:  # a line may name a tool of the repository if it says so
                    named.setdefault(name, []).append(f"{module} {flag}: {line.strip()}")
    assert "edi_live.client" in named
    probe = ("import importlib.util, json, sys\n"
             "def found(name):\n"
             "    try:\n"
             "        return importlib.util.find_spec(name) is not None\n"
             "    except ModuleNotFoundError:  # its parent package is missing\n"
             "        return False\n"
             "print(json.dumps([name for name in sys.argv[1:] if not found(name)]))")
    proc = subprocess.run([sys.executable, "-c", probe, *named], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    missing = json.loads(proc.stdout)
    assert not missing, [named[name] for name in missing]
