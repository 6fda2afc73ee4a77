"""`python -m edi_live` with standard streams a service gives it: stdout into a reader that went away, an ASCII-only
encoding (PYTHONIOENCODING=ascii, as under some init systems), and the unit behaviour of edi_live.console."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

from edi_live import console
from tests.edi_live.test_cli import REPO, _env


def test_list_devices_into_a_closed_pipe_is_not_an_error():
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before anything is written: every write meets EPIPE
    try:
        proc = subprocess.run([sys.executable, "-m", "edi_live", "--list-devices", "--usb-backend",
                               "drivers.emulator:backend"], cwd=REPO, stdout=write_end, stderr=subprocess.PIPE,
                              text=True, timeout=60, env=_env())
    finally:
        os.close(write_end)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""  # no "internal error: BrokenPipeError", no "Exception ignored" at exit


def test_help_on_an_ascii_stdout_is_printed_with_the_micro_sign_escaped():
    proc = subprocess.run([sys.executable, "-m", "edi_live", "--help"], cwd=REPO, capture_output=True, timeout=60,
                          env={**_env(), "PYTHONIOENCODING": "ascii", "LANG": "C", "LC_ALL": "C"})
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == b""
    assert b"APS exposure in \\xb5s" in proc.stdout  # the help text, whole, with "µs" escaped


def test_only_streams_that_cannot_encode_our_text_are_changed(monkeypatch):
    ascii_out = io.TextIOWrapper(io.BytesIO(), encoding="ascii")
    utf8_err = io.TextIOWrapper(io.BytesIO(), encoding="utf-8")
    monkeypatch.setattr(sys, "stdout", ascii_out)
    monkeypatch.setattr(sys, "stderr", utf8_err)
    console.escape_what_cannot_be_encoded()
    assert (ascii_out.errors, utf8_err.errors) == ("backslashreplace", "strict")
    ascii_out.write("1 µs")
    ascii_out.flush()
    assert ascii_out.buffer.getvalue() == b"1 \\xb5s"


def test_list_devices_with_stdout_closed_is_not_an_error():
    proc = subprocess.run([sys.executable, "-m", "edi_live", "--list-devices", "--usb-backend",
                           "drivers.emulator:backend"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True, timeout=60, env=_env(), close_fds=True,
                          preexec_fn=lambda: os.close(1))  # `>&-`: Python starts with sys.stdout None
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_list_devices_into_a_full_disk_is_one_error_line_not_an_internal_error():
    """`edi-live --list-devices > devices.txt` on a full disk said "internal error: OSError: [Errno 28] No space
    left on device (... report it)": a bug to report, where the listing was lost to the disk."""
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "edi_live", "--list-devices", "--usb-backend",
                               "drivers.emulator:backend"], cwd=REPO, stdout=full, stderr=subprocess.PIPE,
                              text=True, timeout=60, env=_env())
    assert proc.returncode == 1
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("edi-live: error: ") and "internal error" not in lines[0], lines
    assert "stdout" in lines[0] and "No space left on device" in lines[0]


def test_with_stderr_closed_the_summary_does_not_land_on_stdout(real_recordings, tmp_path):
    # `2>&-`: sys.stderr is None and print(file=None) writes to stdout, so the summary and error lines went into
    # whatever read stdout; the run itself is unchanged
    out = tmp_path / "sharp.aedat4"
    proc = subprocess.run([sys.executable, "-m", "edi_live", "--replay",
                           str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0", "--no-publish",
                           "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE, text=True, timeout=60, env=_env(),
                          preexec_fn=lambda: os.close(2))
    assert proc.returncode == 0
    assert proc.stdout == ""
    assert out.stat().st_size > 0


_STRAY = b"a library's own message on stderr\n"
_WRAPPER = f"""
import os, sys
import edi_live.writers as writers
from edi_live.cli import main

write_frames = writers.OutWriter._write_frames

def with_a_stray_message(self, recs):
    os.write(2, {_STRAY!r})  # what a C library (libzmq, libusb, OpenCV) does with its messages
    return write_frames(self, recs)

writers.OutWriter._write_frames = with_a_stray_message
sys.exit(main(sys.argv[1:]))
"""


def test_with_stderr_closed_no_recording_takes_its_file_descriptor(real_recordings, tmp_path):
    # `2>&-` left fd 2 free, so the --out file became fd 2 and C-level stderr writes landed inside the recording
    from edi_live.aedat4 import Aedat4Reader

    out = tmp_path / "sharp.aedat4"
    proc = subprocess.run([sys.executable, "-c", _WRAPPER, "--replay",
                           str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0", "--no-publish",
                           "--out", str(out)], cwd=REPO, stdout=subprocess.DEVNULL, timeout=60, env=_env(),
                          preexec_fn=lambda: os.close(2))
    assert proc.returncode == 0
    assert _STRAY not in out.read_bytes()
    with Aedat4Reader(out) as reader:
        assert reader.data_table() is not None and sum(1 for _ in reader) > 0


def _into_a_closed_pipe(*args: str) -> subprocess.CompletedProcess:
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run([sys.executable, "-m", *args], cwd=REPO, stdout=write_end, stderr=subprocess.PIPE,
                              text=True, timeout=60, env=_env())
    finally:
        os.close(write_end)


def test_the_setup_tools_into_a_closed_pipe_end_without_a_traceback(tmp_path):
    # 'python -m drivers.udev | sudo tee RULES' whose tee failed, or a key generation piped into a pager closed
    # early: a BrokenPipeError traceback and exit 1 (the keys had been written)
    keys = _into_a_closed_pipe("edi_live.publisher", "--gen-curve-keys", str(tmp_path / "curve"))
    assert keys.returncode == 0 and keys.stderr == "", keys.stderr
    assert (tmp_path / "curve" / "server.key_secret").is_file()
    rule = _into_a_closed_pipe("drivers.udev")
    assert rule.returncode == 0 and rule.stderr == "", rule.stderr


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
@pytest.mark.parametrize("module,args", [("edi_live.publisher", ("--gen-curve-keys", "curve")), ("drivers.udev", ())])
def test_the_setup_tools_into_a_full_disk_say_so_in_one_line(tmp_path, module, args):
    """'python -m drivers.udev > rules' on a full disk ended in an OSError traceback; so did the key generation
    (whose keys were written, but whose paths the user never saw)."""
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", module, *args], cwd=tmp_path, stdout=full,
                              stderr=subprocess.PIPE, text=True, timeout=60, env=_env())
    assert proc.returncode == 1
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "error: cannot write to stdout (No space left on device)" in lines[0], proc.stderr
