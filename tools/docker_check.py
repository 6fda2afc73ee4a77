"""Build the Docker image and test it like a user: replay a real recording in a container, receive frames on the
host with edi_live.client, stop it with `docker stop`, and check the clean shutdown and the finalised --out file.

    python -m tools.docker_check                        # base python:3.11-slim, pip inside the build
    python -m tools.docker_check --base debian:bookworm-local --wheelhouse
                                                        # a local Debian base; wheels built on the host first

Needs a Docker engine (exit 3 with the reason when none answers; tests/docker/test_image.py then skips).
Prints one JSON line with the figures (build seconds, image bytes, frames received, exit code) and exits 0 only
when every check passed. Runs with `--network host` (builds and runs alike), so it works where the engine has no
bridge network; the container's publisher binds the host's loopback, as edi-live does by default.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RECORDING = REPO.parent / "shared" / "data" / "real" / "emlb_demo-01_davis346.aedat4"
NO_ENGINE = 3


def engine_answers(timeout_s: float = 5.0) -> str | None:
    """None when a Docker engine answers, else why not (one line)."""
    if shutil.which("docker") is None:
        return "no docker client on PATH"
    try:
        proc = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True, text=True,
                              timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return f"the Docker engine did not answer within {timeout_s:.0f} s"
    if proc.returncode != 0:
        return "no Docker engine answers (" + " ".join(proc.stderr.split())[:200] + ")"
    return None


def _run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, **kwargs)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def build(tag: str, base: str | None, wheelhouse: bool) -> float:
    if wheelhouse:  # for builders whose pip cannot reach the index from inside a container (docker/README.md)
        proc = _run([sys.executable, "-m", "pip", "wheel", "--quiet", ".", "-w", "docker/wheelhouse"], cwd=REPO)
        if proc.returncode != 0:
            raise SystemExit(f"pip wheel failed: {proc.stderr[-2000:]}")
    cmd = ["docker", "build", "--network", "host", "-f", "docker/Dockerfile", "-t", tag]
    if base:
        cmd += ["--build-arg", f"BASE={base}"]
    start = time.monotonic()
    proc = _run(cmd + ["."], cwd=REPO)
    seconds = time.monotonic() - start
    if proc.returncode != 0:
        raise SystemExit(f"docker build failed after {seconds:.0f} s: {proc.stdout[-3000:]}{proc.stderr[-2000:]}")
    return seconds


def run_and_stop(tag: str, frames_wanted: int = 20) -> dict:
    from edi_live.aedat4 import Aedat4Reader
    from edi_live.client import Subscriber

    port = _free_port()
    name = f"edi-live-check-{os.getpid()}"
    with tempfile.TemporaryDirectory() as tmp:
        os.chmod(tmp, 0o777)  # the container's user writes --out here
        cmd = ["docker", "run", "-d", "--init", "--network", "host", "--name", name,
               "-v", f"{RECORDING}:/data/rec.aedat4:ro", "-v", f"{tmp}:/out", tag,
               "--replay", "/data/rec.aedat4", "--loop", "--publish", f"tcp://127.0.0.1:{port}",
               "--out", "/out/sharp.aedat4", "--status-interval-s", "60"]
        proc = _run(cmd)
        if proc.returncode != 0:
            raise SystemExit(f"docker run failed: {proc.stderr.strip()}")
        result: dict = {"port": port}
        try:
            received = []
            with Subscriber(f"tcp://127.0.0.1:{port}", newest_only=False) as sub:
                deadline = time.monotonic() + 120
                while len(received) < frames_wanted and time.monotonic() < deadline:
                    got = sub.recv(timeout_s=1.0)
                    if got is not None:
                        received.append((got[0], got[1].shape))
            result["frames_received"] = len(received)
            result["frame_shape"] = list(received[0][1]) if received else None
            result["source"] = received[0][0].get("source") if received else None
            start = time.monotonic()
            _run(["docker", "stop", "-t", "20", name], timeout=60)
            result["stop_s"] = round(time.monotonic() - start, 2)
            state = json.loads(_run(["docker", "inspect", name]).stdout)[0]["State"]
            result["exit_code"] = state["ExitCode"]
            logs = _run(["docker", "logs", name])
            result["summary"] = [line for line in logs.stderr.splitlines() if "done in" in line][-1:]
            result["sigterm_logged"] = "SIGTERM: stopping" in logs.stderr
            out = Path(tmp) / "sharp.aedat4"
            with Aedat4Reader(out) as reader:
                result["out_finalised"] = reader.data_table() is not None
                result["out_frames"] = sum(1 for s, _ in reader if s.type == "FRME")
        finally:
            _run(["docker", "rm", "-f", name])
    result["ok"] = bool(result.get("frames_received") == frames_wanted and result.get("exit_code") == 0
                        and result.get("out_finalised") and result.get("out_frames", 0) > 0 and result["summary"])
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", help="BASE build argument (default: the Dockerfile's, python:3.11-slim)")
    p.add_argument("--wheelhouse", action="store_true", help="build the wheels on the host (docker/wheelhouse/)")
    p.add_argument("--tag", default="edi-live:check")
    p.add_argument("--no-build", action="store_true", help="test an image already built under --tag")
    a = p.parse_args(argv)
    why = engine_answers()
    if why is not None:
        print(json.dumps({"skipped": why}))
        return NO_ENGINE
    figures: dict = {"tag": a.tag, "base": a.base or "python:3.11-slim"}
    if not a.no_build:
        figures["build_s"] = round(build(a.tag, a.base, a.wheelhouse), 1)
    figures["image_bytes"] = int(_run(["docker", "image", "inspect", a.tag, "--format", "{{.Size}}"]).stdout)
    figures.update(run_and_stop(a.tag))
    print(json.dumps(figures))
    return 0 if figures["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
