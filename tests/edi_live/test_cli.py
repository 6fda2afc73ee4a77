"""`python -m edi_live` in subprocesses: exit codes, one-line errors, --help, signals, the --out file.

Every subprocess runs under a timeout; sockets bind random ports (tcp://127.0.0.1:*), read back from the log.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
DEMO = "emlb_demo-01_davis346.aedat4"


def _env() -> dict:
    extra = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": str(REPO) + (os.pathsep + extra if extra else "")}


def run_cli(*args: str, timeout_s: float = 40.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edi_live", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout_s, env=_env())


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("edi-live: error:")]


@pytest.fixture
def needs_reconstructor():
    # a hard import: an import error in the EDI core must fail these tests, not skip them
    import edi_live.reconstructor  # noqa: F401


def _wait_for_a_frame(proc: subprocess.Popen) -> None:
    """Read the node's stderr up to its "publishing on ENDPOINT" line, then receive one frame from it."""
    from edi_live.client import Subscriber

    endpoint = None
    while endpoint is None:
        line = proc.stderr.readline()
        assert line, "the node never reported its endpoint"
        m = re.search(r"publishing on (tcp://\S+)", line)
        endpoint = m.group(1) if m else None
    with Subscriber(endpoint) as sub:
        assert sub.recv(timeout_s=20) is not None, "no frame before the signal"


def test_help_teaches_groups_units_defaults_and_examples():
    proc = run_cli("--help")
    assert proc.returncode == 0
    out = proc.stdout
    for group in ("input (one of)", "device options", "pacing", "EDI reconstruction", "output"):
        assert group in out
    for flag in ("--device", "--replay", "--speed", "--loop", "--duration", "--every", "--c-on", "--mode",
                 "--max-fps", "--publish", "--no-publish", "--curve-secret-key", "--out", "--record", "--config",
                 "--log-level", "--usb-backend", "--list-devices", "--exposure-us"):
        assert flag in out, flag
    assert "tcp://127.0.0.1:5555" in out and "default: 1000" in out and "µs" in out
    examples = [line for line in out.split("examples:")[1].splitlines() if line.strip().startswith("edi-live ")]
    assert len(examples) == 4
    seeing = out.split("seeing the frames:")[1]  # a newcomer learns how to look at the result
    assert "python -m tools.viewer" in seeing and "http://127.0.0.1:8080" in seeing and "--out" in seeing


@pytest.mark.parametrize("args,code,fragment", [
    (("--bogus",), 2, "unrecognized arguments: --bogus"),
    (("--replay", "x.aedat4", "--every", "zero"), 2, "invalid int value"),
    (("--replay", "x.aedat4", "--every", "0"), 2, "every must be an integer in [1, 10^12]"),
    (("--replay", "x.aedat4", "--every", str(10**23)), 2, "every must be an integer in [1, 10^12]"),
    (("--replay", "x.aedat4", "--ring-events", "100000000000"), 2, "of memory is available; choose at most"),
    (("--replay", "x.aedat4", "--publish", "tcp://127.0.0.1:99999"), 2, "port in 1-65535, or *"),
    (("--replay", "x.aedat4", "--publish", "tcp://127.0.0.1:5555", "--no-publish"), 2, "contradict each other"),
    ((), 2, "choose an input"),
    (("--device", "davis240", "--replay", "x.aedat4"), 2, "choose one input"),
    (("--replay", "does-not-exist.aedat4"), 1, "does-not-exist.aedat4: no such file"),
    (("--replay", "tests"), 1, "tests: is a directory, not a recording"),
    (("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--emulate-from", "tests"), 1,
     "tests: is a directory, not a recording"),
    (("--device", "davis240", "--usb-backend", "os:getcwd"), 2, "returned a str, not a pyusb backend"),
    (("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--exposure-us", "999999999"), 2,
     "exposure-us must be at most 4194303 µs"),
    (("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--exposure-us", "0"), 2,
     "exposure-us must be a positive integer"),  # and not, in a second message, "0..4194303"
    (("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--frame-interval-us", "999999999"), 2,
     "frame-interval-us must be at most 8388607 µs"),
    (("--device", "davis240", "--usb-backend", "no_such_module:backend"), 2, "cannot import module"),
    (("--config", "no-such.toml"), 2, "config file no-such.toml not found"),
    # `--config "$CFG"` with CFG unset: the file the user meant was silently not read, the run went on without it
    (("--config", "", "--replay", "x.aedat4"), 2, "config: expected a file path, not an empty one (got '')"),
    # a file or input flag given twice kept the last one in silence: a recording not replayed, an --out not written
    (("--replay", "a.aedat4", "--replay", "b.aedat4"), 2, "--replay given twice ('a.aedat4' and 'b.aedat4')"),
    (("--replay", "x.aedat4", "--out", "a.aedat4", "--out", "b.aedat4"), 2, "--out given twice"),
])
def test_errors_are_one_line_with_the_right_exit_code(args, code, fragment):
    proc = run_cli(*args)
    assert proc.returncode == code, proc.stderr
    lines = error_lines(proc.stderr)
    assert len(lines) == 1 and fragment in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0, "nothing but the one error line"


def test_a_binary_config_is_a_usage_error_and_a_fifo_replay_is_named(tmp_path):
    """Issue 15.7: a binary --config said "internal error ... report it" (exit 1); a FIFO as --replay was
    reported as "no such file"."""
    binary = tmp_path / "photo.toml"
    binary.write_bytes(bytes(range(256)) * 4)
    proc = run_cli("--config", str(binary))
    assert proc.returncode == 2 and error_lines(proc.stderr) == [
        f"edi-live: error: config file {binary} is not a TOML text file (not UTF-8 at byte 128); give --config a "
        f".toml file"], proc.stderr
    fifo = tmp_path / "stream.aedat4"
    os.mkfifo(fifo)
    proc = run_cli("--replay", str(fifo), "--no-publish")
    lines = error_lines(proc.stderr)
    assert proc.returncode == 1 and len(lines) == 1 and "is a FIFO (named pipe), not a regular file" in lines[0]
    assert "no such file" not in proc.stderr


@pytest.mark.skipif(not hasattr(os, "mkfifo") or not Path("/bin/bash").exists(), reason="needs FIFOs and bash")
def test_config_from_a_fifo_without_a_writer_ends_and_from_process_substitution_is_read(tmp_path):
    """--config on a FIFO that nothing writes to blocked in open() for ever; bash's --config <(printf ...) must
    still be read (the unknown key proves the text arrived)."""
    fifo = tmp_path / "edi.toml"
    os.mkfifo(fifo)
    proc = run_cli("--config", str(fifo), "--no-publish")
    lines = error_lines(proc.stderr)
    assert proc.returncode == 2 and len(lines) == 1 and str(fifo) in lines[0] and "pipe" in lines[0], proc.stderr
    script = f"cd {REPO} && exec {sys.executable} -m edi_live --config <(printf 'speed = 0\\nbogus = 1\\n')"
    proc = subprocess.run(["/bin/bash", "-c", script], capture_output=True, text=True, timeout=40, env=_env())
    assert proc.returncode == 2 and error_lines(proc.stderr) == [
        "edi-live: error: config file /dev/fd/63: unknown key(s) bogus"], proc.stderr


def test_not_an_aedat4_file_is_one_line_exit_1(tmp_path):
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(b"this is not an AEDAT4 file at all" * 10)
    proc = run_cli("--replay", str(bad), "--no-publish")
    assert proc.returncode == 1
    assert len(error_lines(proc.stderr)) == 1 and "bad.aedat4" in proc.stderr and "Traceback" not in proc.stderr


def test_debug_log_level_adds_the_traceback(tmp_path):
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(b"x" * 100)
    proc = run_cli("--replay", str(bad), "--no-publish", "--log-level", "debug")
    assert proc.returncode == 1 and "Traceback" in proc.stderr and len(error_lines(proc.stderr)) == 1


def test_list_devices_through_an_emulated_backend():
    proc = run_cli("--list-devices", "--usb-backend", "drivers.emulator:backend")
    assert proc.returncode == 0, proc.stderr
    assert "davis240" in proc.stdout


def test_list_devices_says_which_other_flags_it_ignored():
    # `--list-devices --calibrate-dark 3` listed the cameras and exited 0: the calibration asked for was not done,
    # without a word
    proc = run_cli("--list-devices", "--usb-backend", "drivers.emulator:backend", "--calibrate-dark", "3",
                   "--replay", "x.aedat4")
    assert proc.returncode == 0 and "davis240" in proc.stdout, proc.stderr
    said = [line for line in proc.stderr.splitlines() if "ignored with --list-devices" in line]
    assert len(said) == 1 and "--calibrate-dark" in said[0] and "--replay" in said[0], proc.stderr
    assert "--usb-backend" not in said[0]


def test_replay_speed_0_ends_by_itself_with_a_summary_and_a_dv_readable_out(real_recordings, tmp_path,
                                                                           needs_reconstructor):
    import dv_processing as dv  # the test extra's oracle: required, never skipped
    out = tmp_path / "sharp.aedat4"
    toml = tmp_path / "edi.toml"
    toml.write_text(f'replay = "{real_recordings[DEMO]}"\nspeed = 0\nevery = 5000\n')
    proc = run_cli("--config", str(toml), "--publish", "tcp://127.0.0.1:*", "--out", str(out), timeout_s=60)
    assert proc.returncode == 0, proc.stderr
    assert "done in" in proc.stderr and "13 APS frames in" in proc.stderr
    written = int(re.search(r"--out frames written: (\d+)", proc.stderr).group(1))
    rec = dv.io.MonoCameraRecording(str(out))
    frames = []
    while (f := rec.getNextFrame()) is not None:
        frames.append(f)
    assert len(frames) == written > 13
    assert rec.getFrameResolution() == (346, 260)
    assert [f.timestamp for f in frames] == sorted(f.timestamp for f in frames)
    import aedat  # the second independent reader (test extra)
    frames_b = [p["frame"] for p in aedat.Decoder(str(out)) if "frame" in p]
    assert [f["t"] for f in frames_b] == [f.timestamp for f in frames]
    assert all(np.array_equal(a["pixels"], b.image.squeeze()) for a, b in zip(frames_b, frames))


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


# SIGHUP: the terminal or ssh session went away; its default action killed the node with --out unfinished
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_signals_stop_cleanly_and_finalise_out(real_recordings, tmp_path, sig, needs_reconstructor):
    import dv_processing as dv  # the test extra's oracle: required, never skipped
    out = tmp_path / "sharp.aedat4"
    proc = subprocess.Popen([sys.executable, "-m", "edi_live", "--replay", str(real_recordings[DEMO]), "--loop",
                             "--speed", "1", "--every", "2000", "--publish", "tcp://127.0.0.1:*", "--out", str(out)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=_env(), start_new_session=True)
    try:
        _wait_for_a_frame(proc)
        # to the whole process group, as Ctrl-C in a terminal does: the replay's decoding child gets it too
        os.killpg(proc.pid, sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "done in" in err
    deadline = time.monotonic() + 10
    while _group_alive(proc.pid):
        assert time.monotonic() < deadline, "a child process (the replay's decoder) outlived the node"
        time.sleep(0.05)
    rec = dv.io.MonoCameraRecording(str(out))
    assert rec.getNextFrame() is not None


def test_truncated_recording_exit_1_one_line_and_out_reopens(real_recordings, tmp_path, needs_reconstructor):
    import dv_processing as dv  # the test extra's oracle: required, never skipped
    data = real_recordings[DEMO].read_bytes()
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "sharp.aedat4"
    proc = run_cli("--replay", str(cut), "--speed", "0", "--no-publish", "--every", "3000", "--out", str(out))
    assert proc.returncode == 1, proc.stderr
    lines = error_lines(proc.stderr)
    assert len(lines) == 1 and "cut.aedat4" in lines[0] and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == lines[0], "the error is the last line, after the summary"
    written = int(re.search(r"--out frames written: (\d+)", proc.stderr).group(1))
    rec = dv.io.MonoCameraRecording(str(out))
    n = 0
    while rec.getNextFrame() is not None:
        n += 1
    assert n == written > 0


@pytest.mark.parametrize("device", ["davis346", "davis240"])
def test_emulated_camera_runs_the_whole_node(real_recordings, needs_reconstructor, device):
    # the documented no-camera command: the recording goes through the USB driver's decode path; the
    # emulated camera presents the model asked for (a DAVIS346 file through a DAVIS240 profile too)
    proc = run_cli("--device", device, "--usb-backend", "drivers.emulator:backend", "--emulate-from",
                   str(real_recordings[DEMO]), "--speed", "0", "--no-publish", "--every", "5000", timeout_s=60)
    assert proc.returncode == 0, proc.stderr
    assert "319512 events" in proc.stderr and "13 APS frames in" in proc.stderr and "drops 0" in proc.stderr


def test_importing_the_packages_loads_no_usb_zmq_or_cv2():
    code = ("import sys, drivers, edi_live, edi_live.cli, edi_live.node; "
            "print(sorted(m for m in ('usb', 'zmq', 'cv2') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60,
                          env=_env())
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def _factory_module(tmp_path, monkeypatch, name: str, source: str):
    (tmp_path / f"{name}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib

    return importlib.import_module(name)


def test_usb_backend_factory_gets_the_requested_model(tmp_path, monkeypatch):
    # `--device davis346 --usb-backend drivers.emulator:backend` (no recording) must present a DAVIS346,
    # not the emulator's default DAVIS240
    from edi_live import cli

    mod = _factory_module(tmp_path, monkeypatch, "edi_test_factory_model", (
        "from drivers.emulator import backend as _emulator\n"
        "calls = []\n"
        "def factory(recording=None, *, model=None):\n"
        "    calls.append({'recording': recording, 'model': model})\n"
        "    return _emulator(model=model)\n"))
    config = cli.build_config({"device": "davis346", "usb_backend": "edi_test_factory_model:factory"}, None)
    cli.make_source(config)
    assert mod.calls == [{"recording": None, "model": "davis346"}]
    assert cli.load_usb_backend("drivers.emulator:backend", model="davis346").model.product_id == 0x841A


def test_usb_backend_factory_without_parameters_still_works(tmp_path, monkeypatch):
    # the public hook: CALLABLE() with no arguments; options it does not declare are not forced on it
    from edi_live import cli

    _factory_module(tmp_path, monkeypatch, "edi_test_factory_plain", (
        "from drivers.emulator import backend as _emulator\n"
        "def factory():\n"
        "    return _emulator()\n"))
    backend = cli.load_usb_backend("edi_test_factory_plain:factory", model="davis346", recording="x.aedat4")
    assert callable(backend.enumerate_devices)


class _FakeTerminal:
    def __init__(self, tty: bool) -> None:
        self.tty, self.text = tty, ""

    def isatty(self) -> bool:
        return self.tty

    def write(self, s: str) -> int:
        self.text += s
        return len(s)

    def flush(self) -> None:
        pass


@pytest.mark.parametrize("tty", [True, False])
def test_log_lines_erase_the_live_status_line_on_a_terminal(tty):
    # the status line is drawn with '\r' and no newline; a log record must not be glued to its end
    import logging

    from edi_live import cli, live_line

    stream = _FakeTerminal(tty)
    root = logging.getLogger()
    saved = root.handlers[:], root.level, logging.getLogger("edi_live").level
    try:
        cli._setup_logging("info", stream)
        logging.getLogger("edi_live.node").info("--duration 3.0 s reached")
    finally:
        root.handlers[:], root.level = saved[0], saved[1]
        logging.getLogger("edi_live").setLevel(saved[2])
    expected = "edi-live: INFO: --duration 3.0 s reached\n"
    assert stream.text == (live_line.ERASE + expected if tty else expected)


@pytest.mark.parametrize("endpoints,curve,warned", [
    (["tcp://0.0.0.0:5555"], False, True),
    (["tcp://*:5555"], False, True),
    (["tcp://127.0.0.1:5555", "tcp://192.168.1.4:5555"], False, True),
    (["tcp://127.0.0.1:5555", "ipc:///tmp/edi"], False, False),
    (["tcp://0.0.0.0:5555"], True, False),
])
def test_publishing_beyond_loopback_without_curve_is_said_aloud(caplog, tmp_path, endpoints, curve, warned):
    from edi_live import cli

    flags = {"replay": "x.aedat4", "publish": endpoints}
    if curve:
        flags["curve_secret_key"] = str(tmp_path / "server.key_secret")
    config = cli.build_config(flags, None)
    with caplog.at_level("WARNING", logger="edi_live"):
        cli._warn_if_exposed(config)
    assert any("without encryption" in r.getMessage() for r in caplog.records) == warned


@pytest.mark.parametrize("flags,warning", [
    ({"replay": "x.aedat4", "exposure_us": 5000, "serial": "123"}, "ignored with --replay (camera options): "
                                                                    "--serial, --exposure-us"),
    ({"replay": "x.aedat4", "reconnect": True}, "--reconnect"),
    ({"device": "davis240", "speed": 4.0}, "ignored with a live camera: --speed"),
    ({"replay": "x.aedat4", "speed": 4.0}, None),
    ({"device": "davis240", "exposure_us": 5000}, None),
    ({"replay": "x.aedat4", "latent_denoise": True, "mode": "fused"}, "ignored with --mode fused: --latent-denoise"),
    ({"replay": "x.aedat4", "latent_denoise": True}, None),
    # a fixed c is never estimated: 're-estimated 0 times' in the summary was the only hint
    ({"replay": "x.aedat4", "c": 0.2, "reestimate_every": 5}, "ignored with a fixed c: --reestimate-every"),
    ({"replay": "x.aedat4", "c_on": 0.2, "c_off": 0.3, "reestimate_every": 5}, "--reestimate-every"),
    ({"replay": "x.aedat4", "reestimate_every": 5}, None),
    ({"replay": "x.aedat4", "no_publish": True, "curve_secret_key": "k.key_secret"},
     "ignored with --no-publish: --curve-secret-key"),
])
def test_options_that_do_nothing_for_the_input_are_said_aloud(caplog, flags, warning):
    from edi_live import cli

    config = cli.build_config(flags, None)
    with caplog.at_level("WARNING", logger="edi_live"):
        cli._warn_ignored(config, set(flags))
    messages = [r.getMessage() for r in caplog.records]
    assert (any(warning in m for m in messages) if warning else messages == []), messages


def test_a_huge_every_still_sends_every_moving_deblurred_frame(real_recordings, needs_reconstructor):
    # --every sets the latent frame rate; it must not decide whether an APS frame's sharp L(f) is sent. The
    # Newton's-cradle recording moves in all 13 exposures (the default --every sends all 13).
    proc = run_cli("--replay", str(real_recordings[DEMO]), "--speed", "0", "--no-publish", "--every", "100000000",
                   timeout_s=60)
    assert proc.returncode == 0, proc.stderr
    assert "(13 deblurred" in proc.stderr, proc.stderr


def _out_frames(path: Path) -> int:
    from edi_live.aedat4 import Aedat4Reader

    with Aedat4Reader(path) as reader:
        return sum(1 for stream, _ in reader if stream.type == "FRME")


@pytest.mark.parametrize("gap_s", [0.0, 0.01, 0.05])
def test_a_second_ctrl_c_is_ignored_and_the_summary_matches_out(real_recordings, tmp_path, gap_s,
                                                                needs_reconstructor):
    """Issue 15.2: two SIGINTs close together gave exit 1 ("the out-writer thread failed: KeyboardInterrupt"), a
    summary that disagreed with --out, or death by the signal (rc -2)."""
    out = tmp_path / "sharp.aedat4"
    proc = subprocess.Popen([sys.executable, "-m", "edi_live", "--replay", str(real_recordings[DEMO]), "--loop",
                             "--every", "500", "--publish", "tcp://127.0.0.1:*", "--out", str(out)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        _wait_for_a_frame(proc)
        proc.send_signal(signal.SIGINT)
        time.sleep(gap_s)  # the test's input: the gap between the two Ctrl-Cs (not a synchronisation)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err and not error_lines(err)
    written = int(re.search(r"--out frames written: (\d+)", err).group(1))
    assert written == _out_frames(out) > 0


def test_stderr_into_a_reader_that_went_away_loses_no_frame(real_recordings, tmp_path, needs_reconstructor):
    """'edi-live ... 2>&1 | head -1': the status line's BrokenPipeError left the supervisor loop and stopped the
    run part-way (--out kept 244 of 314 frames, exit 1)."""
    args = ["--replay", str(real_recordings[DEMO]), "--speed", "0", "--no-publish", "--status-interval-s", "0.01"]
    full = tmp_path / "full.aedat4"
    assert run_cli(*args, "--out", str(full), timeout_s=120).returncode == 0
    cut = tmp_path / "cut.aedat4"
    proc = subprocess.Popen([sys.executable, "-m", "edi_live", *args, "--out", str(cut)], cwd=REPO,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=_env())
    try:
        proc.stderr.close()  # the reader is gone before the first status line
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0
    assert _out_frames(cut) == _out_frames(full) > 0


def _fifo_writer_once_read(fifo: Path, proc: subprocess.Popen) -> int:
    """The FIFO's write end, opened once the CLI has its read end open (a non-blocking open of the write end
    succeeds only then): the CLI is in its config read."""
    deadline = time.monotonic() + 30
    while True:
        assert time.monotonic() < deadline and proc.poll() is None, "the CLI never opened its config"
        try:
            return os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        except OSError:  # ENXIO: no reader yet
            threading.Event().wait(0.01)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_sigterm_during_start_up_is_a_clean_stop(real_recordings, tmp_path):
    """Issue 15.3: SIGTERM in the first moments (here: while the config file is being read, through a FIFO that
    blocks until the test writes it) killed the process (rc -15) without a word."""
    fifo = tmp_path / "edi.toml"
    os.mkfifo(fifo)
    out = tmp_path / "sharp.aedat4"
    proc = subprocess.Popen([sys.executable, "-m", "edi_live", "--config", str(fifo), "--replay",
                             str(real_recordings[DEMO]), "--no-publish", "--out", str(out)],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        writer = _fifo_writer_once_read(fifo, proc)
        proc.send_signal(signal.SIGTERM)
        os.write(writer, b"every = 1000\n")
        os.close(writer)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, f"rc {proc.returncode}: {err}"
    assert "SIGTERM: stopping" in err and "Traceback" not in err and not error_lines(err)
    assert not out.exists(), "stopped before the node started: nothing is created"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_ends_the_wait_for_a_config_fifo_that_is_never_written(tmp_path, sig):
    """Ctrl-C while --config waited for a FIFO's writer to write and close it was held until the wait's limit, and
    the run then ended as a usage error (exit 2, "nothing wrote to and closed"). The writer here opens the FIFO and
    never writes or closes it: the signal alone must end the run, cleanly (exit 0, no error line)."""
    fifo = tmp_path / "edi.toml"
    os.mkfifo(fifo)
    proc = subprocess.Popen([sys.executable, "-m", "edi_live", "--config", str(fifo), "--no-publish"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    writer = None
    try:
        writer = _fifo_writer_once_read(fifo, proc)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if writer is not None:
            os.close(writer)
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 0, f"rc {proc.returncode}: {err}"
    assert f"{signal.Signals(sig).name}: stopping" in err and not error_lines(err) and "Traceback" not in err, err


def test_the_emulator_processes_a_truncated_recording_up_to_the_cut_like_replay(real_recordings, tmp_path,
                                                                                needs_reconstructor):
    """Issue 15.4: through the emulated camera a truncated file gave 0 events (the held-back data before the
    fault was dropped with the error); --replay gives everything before the cut. Both must agree."""
    cut = tmp_path / "t.aedat4"
    cut.write_bytes(real_recordings[DEMO].read_bytes()[:1487450])  # the cut, inside a packet
    counts = {}
    for name, args in (("replay", ["--replay", str(cut)]),
                       ("emulator", ["--device", "davis346", "--usb-backend", "drivers.emulator:backend",
                                     "--emulate-from", str(cut)])):
        proc = run_cli(*args, "--speed", "0", "--no-publish", timeout_s=90)
        assert proc.returncode == 1, proc.stderr
        lines = error_lines(proc.stderr)
        assert len(lines) == 1 and "t.aedat4 at byte" in lines[0] and "truncated" in lines[0], proc.stderr
        counts[name] = int(re.search(r"done in [\d.]+ s: (\d+) events", proc.stderr).group(1))
    assert counts["emulator"] == counts["replay"] > 100_000


def _packet_at(data: bytes, index: int) -> int:
    """File offset of packet `index` (walked from the header, independently of the reader)."""
    import struct

    pos = 18 + struct.unpack_from("<I", data, 14)[0]
    for _ in range(index):
        pos += 8 + struct.unpack_from("<i", data, pos + 4)[0]
    return pos


@pytest.mark.parametrize("damage", ["stream id 77", "table cut by 7 bytes"])
def test_damage_is_one_error_line_after_the_summary_never_a_silent_exit_0(real_recordings, tmp_path, damage,
                                                                          needs_reconstructor):
    """Issue 15.6, the damage policy: every kind of damage is processed up to the fault, then one line names the
    file and byte and the exit code is 1. Before: a raw RuntimeWarning, 335 events lost behind "drops 0" and exit
    0 (corrupt stream id); exit 0 without a word (a FileDataTable cut short, which dv-processing refuses)."""
    import struct

    data = bytearray(real_recordings[DEMO].read_bytes())
    if damage == "stream id 77":
        at = _packet_at(data, 600)
        struct.pack_into("<i", data, at, 77)
    else:
        del data[-7:]
    bad = tmp_path / "damaged.aedat4"
    bad.write_bytes(bytes(data))
    out = tmp_path / "sharp.aedat4"
    proc = run_cli("--replay", str(bad), "--speed", "0", "--no-publish", "--out", str(out), timeout_s=90)
    assert proc.returncode == 1, proc.stderr
    lines = error_lines(proc.stderr)
    assert len(lines) == 1 and f"{bad} at byte" in lines[0], proc.stderr
    if damage == "stream id 77":
        assert f"at byte {at}:" in lines[0] and "stream 77" in lines[0]
    else:
        assert "FileDataTable" in lines[0]
    assert proc.stderr.strip().splitlines()[-1] == lines[0], "the error is the last line, after the summary"
    assert "Warning" not in proc.stderr.replace("edi-live: WARNING", "") and "Traceback" not in proc.stderr
    written = int(re.search(r"--out frames written: (\d+)", proc.stderr).group(1))
    assert written == _out_frames(out) > 0


def test_a_colour_camera_says_colour_in_the_listing_and_the_summary():
    listed = run_cli("--list-devices", "--usb-backend", "drivers.emulator:colour_backend")
    assert listed.returncode == 0, listed.stderr
    assert "davis346" in listed.stdout and "colour (RGGB Bayer)" in listed.stdout
    proc = run_cli("--device", "davis346", "--usb-backend", "drivers.emulator:colour_backend", "--no-publish",
                   "--duration", "1", "--latent-denoise", timeout_s=90)
    assert proc.returncode == 0, proc.stderr
    assert "WARNING: ignored with a colour camera: --latent-denoise" in proc.stderr  # it did nothing, silently
    assert "done in" in proc.stderr and "camera: DAVIS346_EMUCRGGB 346x260, colour (RGGB Bayer mosaic)" in proc.stderr
    assert "INFO: DAVIS davis346 at USB 1:7 is a colour DAVIS346: RGGB Bayer mosaic" in proc.stderr  # at start-up


@pytest.mark.parametrize("flags, warned", [
    (["--bayer-pattern", "GBRG"], True),  # a mosaic stored as grey: colour from the first frame
    (["--bayer-pattern", "GBRG", "--gray"], True),  # grey output, still EDI on the mosaic
    ([], False),  # a grey camera: the filter does its work
    (["--bayer-pattern", "GBRG", "--mode", "nearest"], False),  # said once, by the --mode warning
])
def test_latent_denoise_on_a_mosaic_is_said_to_do_nothing(real_recordings, needs_reconstructor, flags, warned):
    proc = run_cli("--replay", str(real_recordings[DEMO]), "--speed", "0", "--no-publish", "--duration", "0.05",
                   "--latent-denoise", *flags, timeout_s=90)
    assert proc.returncode == 0, proc.stderr
    assert ("ignored with a colour camera: --latent-denoise" in proc.stderr) == warned, proc.stderr


def _bgr_recording(path: Path) -> None:
    """A small colour scene written the way DV records a colour camera: demosaiced BGR frames, no pattern named."""
    from edi_live.aedat4 import Aedat4Writer
    from edi_live.colour import demosaic
    from edi_live.datatypes import Frame
    from edi_live.simulation import SceneConfig, simulate

    sim = simulate(SceneConfig(width=48, height=32, duration_s=0.3, color_filter="RGGB",
                               velocity_px_s=(100.0, 20.0)))
    with Aedat4Writer(path, 48, 32, events=True, frames=True, camera_name="dv-colour") as writer:
        lo = -1
        for f in sim.frames:
            writer.write_events(sim.events[(sim.events["t"] > lo) & (sim.events["t"] <= f.exposure_end_us)])
            writer.write_frame(Frame(demosaic(f.image, "RGGB"), f.exposure_start_us, f.exposure_end_us))
            lo = f.exposure_end_us


@pytest.mark.parametrize("flags, said", [
    ([], None),
    (["--latent-denoise"], "  --latent-denoise was ignored: the source's frames were colour (BGR)"),
    (["--latent-denoise", "--bayer-pattern", "GBRG"], None),  # warned at start-up instead
])
def test_a_bgr_recording_is_summarised_as_colour(tmp_path, needs_reconstructor, flags, said):
    # its summary had no camera line (the file does not say colour) and --latent-denoise was dropped unsaid
    path = tmp_path / "bgr.aedat4"
    _bgr_recording(path)
    proc = run_cli("--replay", str(path), "--speed", "0", "--no-publish", *flags, timeout_s=90)
    assert proc.returncode == 0, proc.stderr
    pattern = "GBRG Bayer mosaic given by --bayer-pattern" if "--bayer-pattern" in flags else \
        "RGGB Bayer mosaic, the source's BGR frames re-mosaiced"
    assert f"  camera: dv-colour 48x32, colour ({pattern})" in proc.stderr.splitlines(), proc.stderr
    assert [line for line in proc.stderr.splitlines() if "was ignored" in line] == ([said] if said else [])


def test_the_duration_reached_is_said_as_given(real_recordings, needs_reconstructor):
    # '--duration 0.05' said '--duration 0.1 s reached' (and 1e-9 said '0.0 s')
    proc = run_cli("--replay", str(real_recordings[DEMO]), "--loop", "--speed", "0", "--no-publish", "--duration",
                   "0.05", timeout_s=90)
    assert proc.returncode == 0 and "--duration 0.05 s reached" in proc.stderr, proc.stderr


@pytest.mark.parametrize("flag", ["out", "record", "save_calibration"])
def test_outputs_never_overwrite_the_config_file(tmp_path, monkeypatch, flag):
    # '--config run.toml --out run.toml' replaced the user's options file with the run's AEDAT4 output
    from edi_live import cli
    from edi_live.errors import ConfigError

    config = tmp_path / "run.toml"
    config.write_text("every = 500\n")
    monkeypatch.chdir(tmp_path)
    for written in ("run.toml", str(config), "./run.toml"):
        with pytest.raises(ConfigError, match=f"{flag.replace('_', '-')} would overwrite the config file"):
            cli.build_config({"replay": "x.aedat4", flag: written}, config)
    assert config.read_text() == "every = 500\n"
    assert cli.build_config({"replay": "x.aedat4", flag: "other.aedat4"}, config) is not None
