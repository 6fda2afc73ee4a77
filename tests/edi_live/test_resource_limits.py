"""Running out of memory under a limit (`ulimit -v`) is one line naming the limit, not an internal error."""

from __future__ import annotations

import resource
import subprocess
import sys

from edi_live.errors import NodeError, ResourceError
from edi_live.resource_limits import out_of_memory
from tests.edi_live.test_cli import DEMO, REPO, _env, error_lines

LIMIT = 1536 * 2**20  # address space; a 1 GiB ring cannot fit beside the interpreter, numpy and numba under it


def _limited() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (LIMIT, LIMIT))


def test_a_ring_larger_than_the_memory_limit_is_one_line_naming_the_limit(real_recordings, tmp_path):
    args = ["--replay", str(real_recordings[DEMO]), "--speed", "0", "--no-publish", "--ring-events", str(2**26)]
    proc = subprocess.run([sys.executable, "-m", "edi_live", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env=_env(), preexec_fn=_limited)
    assert proc.returncode == 1
    (line,) = error_lines(proc.stderr)
    assert "out of memory" in line and f"ulimit -v {LIMIT // 1024}" in line
    assert "internal error" not in line and "Traceback" not in proc.stderr


def test_causes_are_found_through_the_chain_and_other_errors_are_left_alone():
    try:
        try:
            raise ImportError("/x/cv2.abi3.so: failed to map segment from shared object")
        except ImportError as exc:
            raise NodeError("the main thread failed: ImportError: ...") from exc
    except NodeError as wrapped:
        found = out_of_memory(wrapped)
    assert isinstance(found, ResourceError) and "cv2.abi3.so: failed to map segment" in str(found)
    try:
        try:
            raise OSError("failed to map segment from shared object")
        except OSError:
            raise OSError("Could not find/load shared object file 'libllvmlite.so'")  # llvmlite's, during handling
    except OSError as raised:
        assert out_of_memory(raised) is not None
    assert isinstance(out_of_memory(MemoryError()), ResourceError)
    assert out_of_memory(NodeError("the edi-worker thread failed: ValueError: x")) is None
    assert out_of_memory(FileNotFoundError(2, "No such file or directory")) is None


def _few_files() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))


def test_a_low_open_files_limit_is_said_at_start_when_publishing(real_recordings):
    # under `ulimit -n 64` 48 of 100 subscribers were served and the node said nothing about the rest
    args = ["--replay", str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0", "--publish",
            "tcp://127.0.0.1:*"]
    proc = subprocess.run([sys.executable, "-m", "edi_live", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env=_env(), preexec_fn=_few_files)
    assert proc.returncode == 0, proc.stderr
    assert "only 64 open files are allowed (ulimit -n)" in proc.stderr
    quiet = subprocess.run([sys.executable, "-m", "edi_live", *args[:4], "--no-publish"], cwd=REPO,
                           capture_output=True, text=True, timeout=120, env=_env(), preexec_fn=_few_files)
    assert quiet.returncode == 0 and "open files" not in quiet.stderr  # nothing to subscribe to: nothing to say
