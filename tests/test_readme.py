"""The README's promises, run as a user would run them.

- `.ci/run` calls exactly the test command the README gives.
- The first setup command (simulate a recording, replay it through the node with --out) produces sharp frames:
  the deblurred frames in --out beat the blurry APS frames against the simulator's ground truth.
- `python -m tools.figure` (the README picture) writes a non-blank image.

Tools run as `python -m tools.NAME` from the repository root; the subprocesses here get it through PYTHONPATH.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def _readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    block = text.split("## Set up and run: two commands", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    return [ln.strip() for ln in block.splitlines() if ln.strip() and not ln.strip().startswith("#")]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def test_readme_has_two_setup_commands_and_ci_runs_the_test_one():
    install_and_run, test = _readme_commands()
    assert "pip install" in install_and_run and "edi-live --replay" in install_and_run
    ci = [ln.strip() for ln in (REPO / ".ci/run").read_text().splitlines()
          if ln.strip() and not ln.lstrip().startswith("#")]
    assert ci[-1] == test, f".ci/run must end with the README's test command {test!r}"


def test_the_first_readme_command_installs_into_a_virtual_environment():
    """Debian 12 and Ubuntu 23.04+ mark their Python as externally managed: a bare `pip install -e .` there stops
    with "error: externally-managed-environment" before anything is installed. The command makes and activates a
    venv first (`.` keeps it active for command 2 in the same shell)."""
    install_and_run, _ = _readme_commands()
    steps = [s.strip() for s in install_and_run.split("&&")]
    pip = next(i for i, s in enumerate(steps) if s.startswith("pip install"))
    assert re.fullmatch(r"python3? -m venv (\S+)", steps[0]), steps
    venv = steps[0].split()[-1]
    assert f". {venv}/bin/activate" in steps[1:pip], steps


def test_first_readme_command_deblurs_the_simulated_recording(tmp_path):
    from edi_live.aedat4.reader import Aedat4Reader
    from tools.simulate import load_ground_truth

    install_and_run, _ = _readme_commands()
    # skip the venv and install steps (the suite already runs installed), keep the rest verbatim, shorten the recording
    steps = [s.strip() for s in install_and_run.split("&&")
             if not s.strip().startswith(("pip ", "python3 -m venv ", ". "))]
    assert re.match(r"python -m tools\.simulate demo\.aedat4$", steps[0]) and steps[1].startswith("edi-live ")
    sim = subprocess.run([sys.executable, *steps[0].split()[1:], "--duration-s", "0.5"],
                         cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=120)
    assert sim.returncode == 0, sim.stderr
    node_args = steps[1].split()[1:] + ["--speed", "0", "--no-publish"]
    node = subprocess.run([sys.executable, "-m", "edi_live", *node_args], cwd=tmp_path, env=_env(),
                          capture_output=True, text=True, timeout=120)
    assert node.returncode == 0, node.stderr
    assert "Traceback" not in node.stderr

    gt = load_ground_truth(tmp_path / "demo.npz")
    mids = {int(t): i for i, (t, k) in enumerate(zip(gt["gt_t_us"], gt["gt_kind"])) if k == 0}
    aps_by_mid = {int(t): gt["aps_images"][int(f)] for t, k, f in zip(gt["gt_t_us"], gt["gt_kind"], gt["gt_frame"])
                  if k == 0}
    sharp, blurry = [], []
    # a deblurred frame is stamped at its mid-exposure in the event clock: the APS clock plus the offset in use,
    # 0 until the node has found one (from the 4th frame), then the one the summary reports
    offset = int(re.search(r"clock offset (-?\d+) µs", node.stderr).group(1))
    with Aedat4Reader(tmp_path / "sharp.aedat4") as reader:
        for _stream, item in reader:
            t = getattr(item, "exposure_start_us", None)
            mid = t if t in mids else t - offset if t is not None and t - offset in mids else None
            if mid is not None and int(mid) != min(mids):  # the first APS frame has no c estimate yet
                truth = gt["gt_images"][mids[mid]]
                sharp.append(_psnr(item.image, truth))
                blurry.append(_psnr(aps_by_mid[mid], truth))
    assert len(sharp) >= 3, "the --out file should hold the deblurred APS frames"
    assert np.mean(sharp) > np.mean(blurry) + 0.5, (np.mean(sharp), np.mean(blurry))


def test_figure_tool_writes_a_non_blank_picture(tmp_path, real_recordings):
    import cv2

    out = tmp_path / "fig.png"
    proc = subprocess.run([sys.executable, "-m", "tools.figure", str(out), "--real",
                           str(real_recordings["emlb_demo-01_davis346.aedat4"])],
                          cwd=REPO, env=_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert img is not None and img.shape[0] == 400  # two rows: simulated and real
    assert img.std() > 20
