"""`edi-live` with a camera through `--usb-backend` (the emulator, or a user's own backend module): what the user
sees when the backend module is broken, or the camera goes away mid-run. Subprocesses, real files, the emulator.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _run(tmp_path: Path, *args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """The node with `tmp_path` importable, so a backend module written there can be named by --usb-backend."""
    path = os.pathsep.join([str(REPO), str(tmp_path)] + ([os.environ["PYTHONPATH"]] if "PYTHONPATH" in os.environ
                                                         else []))
    return subprocess.run([sys.executable, "-m", "edi_live", "--no-publish", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout_s, env={**os.environ, "PYTHONPATH": path})


def _error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("edi-live: error:")]


# A backend module that fails while it is imported (a typo, or its own error) was reported as our bug:
# "internal error: SyntaxError: ... (rerun with --log-level debug for the traceback and report it)".
@pytest.mark.parametrize("source, what", [("def backend(:\n", "SyntaxError"),
                                          ("raise RuntimeError('no licence file')\n", "no licence file")])
@pytest.mark.parametrize("command", [["--device", "davis346"], ["--list-devices"]])
def test_a_backend_module_that_fails_to_import_is_named_as_a_usage_error(tmp_path, source, what, command):
    (tmp_path / "edi_test_broken_backend.py").write_text(source)
    proc = _run(tmp_path, *command, "--usb-backend", "edi_test_broken_backend:backend")
    lines = _error_lines(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and "--usb-backend edi_test_broken_backend:backend" in lines[0] and what in lines[0]
    assert "internal error" not in proc.stderr and "Traceback" not in proc.stderr


# A backend whose device enumeration raises something other than a pyusb error ended the run with "the main
# thread failed: OSError: ..." and --list-devices with "internal error ... report it".
@pytest.mark.parametrize("command", [["--device", "davis346"], ["--list-devices"]])
def test_a_backend_that_fails_to_enumerate_is_one_line_naming_the_usb_bus(tmp_path, command):
    (tmp_path / "edi_test_enum_backend.py").write_text(
        "class _Backend:\n"
        "    def enumerate_devices(self):\n"
        "        raise OSError(5, 'the hub went away')\n"
        "def backend():\n"
        "    return _Backend()\n")
    proc = _run(tmp_path, *command, "--usb-backend", "edi_test_enum_backend:backend")
    lines = _error_lines(proc.stderr)
    assert proc.returncode == 1, proc.stderr
    assert len(lines) == 1 and "USB" in lines[0] and "the hub went away" in lines[0]
    assert "internal error" not in proc.stderr and "main thread failed" not in proc.stderr
