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


_GONE_WHILE_STARTING = '''
import errno, time
import usb.core
from drivers.emulator import EmulatorBackend

class _GoneWhileStarting(EmulatorBackend):
    """An emulated camera whose cable fails during the driver's start sequence (its 13th control transfer)."""
    transfers = 0

    def ctrl_transfer(self, *args):
        type(self).transfers += 1
        if type(self).transfers == 13:
            self._unplugged_at = time.monotonic()
            raise usb.core.USBError("No such device", -4, errno.ENODEV)
        return super().ctrl_transfer(*args)

def comes_back(recording=None, **options):
    return _GoneWhileStarting(recording, replug_after_s=0.3, **options)

def stays_away(recording=None, **options):
    return _GoneWhileStarting(recording, **options)
'''


# A camera that went away while the driver started it ended the run with "... was disconnected; check the cable,
# or run with --reconnect", with --reconnect given: --reconnect covered only unplugs after streaming had begun.
def test_with_reconnect_a_camera_gone_while_starting_is_waited_for(tmp_path, real_recordings):
    (tmp_path / "edi_test_gone_while_starting.py").write_text(_GONE_WHILE_STARTING)
    out = tmp_path / "out.aedat4"
    proc = _run(tmp_path, "--device", "davis346", "--usb-backend", "edi_test_gone_while_starting:comes_back",
                "--emulate-from", str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0",
                "--reconnect", "--c", "0.3", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "waiting for it to come back" in proc.stderr and "is back after" in proc.stderr
    assert not _error_lines(proc.stderr)
    import dv_processing as dv

    reader = dv.io.MonoCameraRecording(str(out))
    frames = 0
    while reader.getNextFrame() is not None:
        frames += 1
    assert frames > 0  # the recording was streamed and reconstructed once the camera was back


def _interrupted_while_the_camera_stays_away(tmp_path, real_recordings, *args: str) -> tuple[int, str]:
    """Run edi-live on a camera that is gone while the driver starts it, with --reconnect, and SIGINT it once it
    says it waits: (exit code, stderr)."""
    import signal

    (tmp_path / "edi_test_gone_while_starting.py").write_text(_GONE_WHILE_STARTING)
    path = os.pathsep.join([str(REPO), str(tmp_path)])
    proc = subprocess.Popen([sys.executable, "-m", "edi_live", "--device", "davis346", "--usb-backend",
                             "edi_test_gone_while_starting:stays_away", "--emulate-from",
                             str(real_recordings["evlib_sample_davis346.aedat4"]), "--reconnect", *args],
                            cwd=REPO, stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": path})
    try:
        seen = []
        for line in proc.stderr:  # synchronise on the node saying it waits
            seen.append(line)
            if "waiting for it to come back" in line:
                break
        else:
            raise AssertionError("".join(seen))
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=30)  # (before reading: a node that never ends must fail here, not hang the read)
        return code, "".join(seen) + proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_stop_signal_ends_the_wait_for_a_camera_gone_while_starting(tmp_path, real_recordings):
    code, err = _interrupted_while_the_camera_stays_away(tmp_path, real_recordings, "--no-publish", "--out",
                                                         str(tmp_path / "out.aedat4"))
    assert code == 0, err
    assert not _error_lines(err)


def test_a_stop_signal_ends_calibrate_dark_waiting_for_a_camera_gone_while_starting(tmp_path, real_recordings):
    # --calibrate-dark stops through its own handle on the signal: it must reach the source's wait as the node's does
    target = tmp_path / "dark.json"
    code, err = _interrupted_while_the_camera_stays_away(tmp_path, real_recordings, "--calibrate-dark", "5",
                                                         "--save-calibration", str(target))
    assert code == 1, err
    lines = _error_lines(err)
    assert len(lines) == 1 and "stopped after 0 of 5 APS frames; nothing written" in lines[0]
    assert not target.exists()


@pytest.mark.parametrize("spec", ["drivers.emulator", ":", "drivers.emulator:", ":backend"])
def test_a_backend_without_module_or_callable_says_the_form(spec):
    # "drivers.emulator" (the colon forgotten) was "module 'drivers.emulator' has no callable ''", and ":" was
    # "importing module '' failed (ValueError: Empty module name)": neither says what to write
    from edi_live.cli import load_usb_backend
    from edi_live.errors import ConfigError

    with pytest.raises(ConfigError, match="MODULE:CALLABLE"):
        load_usb_backend(spec)
