"""docker/: static checks that need no Docker daemon. What the image copies exists and is not excluded by the
dockerignore, the udev rule ships, and the edi-live commands the build runs (the JIT warm-up) parse and run."""

from __future__ import annotations

import fnmatch
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCKERFILE = REPO / "docker" / "Dockerfile"


def _instructions() -> list[str]:
    text = DOCKERFILE.read_text().replace("\\\n", " ")
    return [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _ignored(path: str) -> bool:
    """Docker's rule: the last matching pattern wins; '!' re-includes."""
    ignored = False
    for raw in (REPO / "docker" / "Dockerfile.dockerignore").read_text().splitlines():
        pattern = raw.strip()
        if not pattern or pattern.startswith("#"):
            continue
        negate = pattern.startswith("!")
        pattern = pattern.lstrip("!").rstrip("/")
        if fnmatch.fnmatch(path, pattern) or path.startswith(pattern + "/"):
            ignored = not negate
    return ignored


def test_every_copied_path_exists_and_is_in_the_build_context():
    copies = [line.split()[1:-1] for line in _instructions() if line.startswith("COPY ")]
    sources = [s for srcs in copies for s in srcs if not s.startswith("--")]
    assert "drivers/99-edi-live-davis.rules" in sources, "the udev rule must ship in the image"
    for source in sources:
        if "*" in source:  # optional inputs (docker/wheelhouse*): may be absent, must not be excluded
            assert not _ignored(source.rstrip("*")), f"{source} is excluded by Dockerfile.dockerignore"
            continue
        assert (REPO / source).exists(), source
        assert not _ignored(source), f"{source} is excluded by Dockerfile.dockerignore"


def test_the_jit_warm_up_commands_run(tmp_path):
    # the build compiles the numba kernels by running edi-live; here the same commands run outside Docker
    # (with a fresh cache folder) so a renamed flag or a broken emulator cannot break the image build unseen
    runs = [line[4:] for line in _instructions() if line.startswith("RUN ") and "edi-live " in line]
    assert runs, "the Dockerfile no longer warms the JIT cache"
    env_lines = [line for line in _instructions() if line.startswith("ENV NUMBA_CACHE_DIR=")]
    assert env_lines, "NUMBA_CACHE_DIR must point at a folder the image keeps"
    ran = 0
    for step in re.split(r"\s*&&\s*", runs[0]):
        argv = [a.replace("/tmp/", f"{tmp_path}/") for a in shlex.split(step)]
        assigned = {}
        while argv and re.fullmatch(r"[A-Z_]+=\S*", argv[0]):  # VAR=value before the command, as sh reads it
            name, _, value = argv.pop(0).partition("=")
            assigned[name] = value
        if not argv or argv[0] != "edi-live":
            continue
        proc = subprocess.run([sys.executable, "-m", "edi_live", *argv[1:]], cwd=REPO, capture_output=True,
                              text=True, timeout=120,
                              env={**os.environ, "PYTHONPATH": str(REPO),
                                   "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache"), **assigned})
        assert proc.returncode == 0, f"{step}: {proc.stderr[-800:]}"
        ran += 1
    assert ran == 2, "the warm-up runs the emulated camera and a replay"


@pytest.mark.parametrize("args,publishes", [
    (["--replay", "x.aedat4"], True),
    (["--replay", "x.aedat4", "--no-publish"], False),
    (["--replay", "x.aedat4", "--publish", "tcp://0.0.0.0:6000"], False),
    (["--help"], False),
    (["--list-devices"], False),
])
def test_entrypoint_adds_the_container_endpoint_only_when_the_user_did_not_choose(tmp_path, args, publishes):
    fake = tmp_path / "edi-live"
    fake.write_text('#!/bin/sh\nfor a in "$@"; do echo "$a"; done\n')
    fake.chmod(0o755)
    proc = subprocess.run(["sh", str(REPO / "docker" / "entrypoint.sh"), *args], capture_output=True, text=True,
                          timeout=30, env={"PATH": f"{tmp_path}:/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    argv = proc.stdout.splitlines()
    assert argv[-len(args):] == args
    assert (argv[:2] == ["--publish", "tcp://0.0.0.0:5555"]) == publishes
