"""Saved calibrations: round trip, refusal of another camera's or a damaged file, and the node's use of them
(--save-calibration / --calibration on a replay; a live camera, here the emulated one, picks up its own)."""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from edi_live import calibration
from edi_live.datatypes import SourceInfo
from edi_live.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
CAM = SourceInfo(346, 260, "DAVIS346", "00000391", "usb")


def test_a_saved_calibration_reads_back_equal(tmp_path):
    cal = calibration.Calibration(CAM.label, 346, 260, 0.31, 0.27, 4.5)
    calibration.save(cal, tmp_path / "sub" / "cam.json")
    back = calibration.load(tmp_path / "sub" / "cam.json")
    assert (back.camera, back.width, back.height, back.c_on, back.c_off, back.black_level) == \
           (CAM.label, 346, 260, 0.31, 0.27, 4.5)
    back.check_for(CAM, "cam.json")  # its own camera: accepted


def test_a_hand_edited_calibration_saved_with_a_byte_order_mark_is_read(tmp_path):
    # the file is meant to be mended by hand; Notepad saves UTF-8 with a BOM, which json refused ("Unexpected UTF-8
    # BOM"), so the mended file stopped the run
    path = tmp_path / "cam.json"
    calibration.save(calibration.Calibration(CAM.label, 346, 260, 0.31, 0.27, 4.5), path)
    path.write_bytes(path.read_text(encoding="utf-8").encode("utf-8-sig"))
    assert calibration.load(path).c_on == 0.31


@pytest.mark.parametrize("other", [SourceInfo(346, 260, "DAVIS346", "00000104"), SourceInfo(240, 180, "DAVIS346",
                                                                                            "00000391")])
def test_another_cameras_calibration_is_refused_in_one_line(tmp_path, other):
    calibration.save(calibration.Calibration(CAM.label, 346, 260, 0.3, 0.3), tmp_path / "cam.json")
    with pytest.raises(ConfigError) as info:
        calibration.load(tmp_path / "cam.json").check_for(other, tmp_path / "cam.json")
    text = str(info.value)
    assert "\n" not in text and CAM.label in text and other.label in text and f"{other.width}x{other.height}" in text


@pytest.mark.parametrize("content", ["not json", "[]", '{"format": "edi-live calibration", "version": 1}',
                                     json.dumps({"format": "edi-live calibration", "version": 1, "camera": "X",
                                                 "width": 4, "height": 3, "c_on": 9.0, "c_off": 0.2}),
                                     json.dumps({"format": "something else", "version": 1})])
def test_a_damaged_calibration_is_one_config_error(tmp_path, content):
    path = tmp_path / "bad.json"
    path.write_text(content)
    with pytest.raises(ConfigError, match="calibration"):
        calibration.load(path)
    with pytest.raises(ConfigError, match="cannot read"):
        calibration.load(tmp_path / "missing.json")


def test_a_calibration_saved_through_a_symlink_replaces_its_target_and_keeps_the_link(tmp_path):
    """--save-calibration to a symbolic link (a calibration kept with a user's dotfiles) replaced the link with a
    regular file: the file the link pointed at kept the old values."""
    target = tmp_path / "dotfiles" / "cam.json"
    calibration.save(calibration.Calibration(CAM.label, 346, 260, 0.2, 0.2), target)
    link = tmp_path / "cam.json"
    link.symlink_to(target)
    calibration.save(calibration.Calibration(CAM.label, 346, 260, 0.31, 0.27, 4.5), link)
    assert link.is_symlink() and calibration.load(target).c_on == 0.31


def _hand_edited(**changes: object) -> str:
    good = {"format": "edi-live calibration", "version": 1, "camera": CAM.label, "width": 346, "height": 260,
            "c_on": 0.3, "c_off": 0.3}
    return json.dumps({**good, **changes})


# A hand-edited number too large for a float, and arrays nested deeper than the JSON parser recurses, ended the
# node with "the main thread failed: OverflowError" / "RecursionError" instead of naming the file.
@pytest.mark.parametrize("content", [_hand_edited(clock_offset_us=10**400), _hand_edited(black_level=-10**400),
                                     _hand_edited(c_on=10**400), "[" * 100_000 + "]" * 100_000,
                                     '{"noise": ' + "[" * 100_000 + "]" * 100_000 + "}"],
                         ids=["offset-1e400", "black-level--1e400", "c-on-1e400", "nested-list", "nested-noise"])
def test_a_hand_edited_calibration_beyond_what_json_numbers_or_nesting_allow_is_one_config_error(tmp_path, content):
    path = tmp_path / "edited.json"
    path.write_text(content)
    with pytest.raises(ConfigError, match="calibration") as info:
        calibration.load(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("field,value", [("clock_offset_us", 1e30), ("clock_offset_us", 1.5), ("aps_gamma", 0),
                                         ("black_level_measured", "yes"), ("width", "346"), ("c_off", None)])
def test_a_value_out_of_range_is_named_with_its_field(tmp_path, field, value):
    """Every value out of range was refused as "holds values out of range (c in [0.01, 2], black level in
    [0, 128))", also a clock offset of 1e30 or an APS gamma of 0: the user was pointed at fields that were fine."""
    path = tmp_path / "edited.json"
    path.write_text(_hand_edited(**{field: value}))
    with pytest.raises(ConfigError) as info:
        calibration.load(path)
    message = str(info.value)
    assert str(path) in message and f"{field}={value!r}" in message
    others = {"c_on", "c_off", "black_level", "clock_offset_us", "aps_gamma", "width"} - {field}
    assert not any(f"{other}=" in message for other in others), message


def test_noise_rates_that_inflate_far_beyond_their_size_are_refused_without_inflating_them(tmp_path):
    # 2 GiB of zeros compress to 2 MB: such a file used to be inflated whole (a 4 GiB one took 8.7 GB of memory
    # and 21 s; a 64 MB file would have been killed by the kernel) before its size was found wrong
    import base64
    import resource
    import zlib

    deflate = zlib.compressobj(9)
    block = bytes(1 << 24)
    blob = b"".join([deflate.compress(block) for _ in range(128)] + [deflate.flush()])
    on_hz = base64.b64encode(blob).decode("ascii")
    rates = {"encoding": "zlib+base64 float16 little-endian, row-major (height, width)", "shape": [260, 346],
             "on_hz": on_hz, "off_hz": on_hz, "seconds": on_hz}
    path = tmp_path / "bomb.json"
    path.write_text(_hand_edited(noise=rates))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(ConfigError, match="per-pixel noise rates 'on_hz'"):
        calibration.load(path)
    grown_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
    assert grown_kb < 1 << 19, f"loading grew the process by {grown_kb} kB"


def _node(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edi_live", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=90, env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})})


def test_the_node_saves_and_starts_from_a_calibration(real_recordings, tmp_path):
    emlb = str(real_recordings["emlb_demo-01_davis346.aedat4"])
    saved = tmp_path / "emlb.json"
    first = _node("--replay", emlb, "--speed", "0", "--no-publish", "--save-calibration", str(saved))
    assert first.returncode == 0, first.stderr
    cal = calibration.load(saved)
    assert cal.camera == "DAVIS346_00000391" and f"c_on={cal.c_on:.4f}" in first.stderr
    second = _node("--replay", emlb, "--speed", "0", "--no-publish", "--calibration", str(saved))
    assert second.returncode == 0 and "starting from the calibration" in second.stderr
    other = _node("--replay", str(real_recordings["aestream_davis346.aedat4"]), "--speed", "0", "--no-publish",
                  "--calibration", str(saved))
    errors = [line for line in other.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert other.returncode == 2 and len(errors) == 1 and "DAVIS346_00000391" in errors[0], other.stderr


def test_a_run_that_measured_nothing_leaves_the_saved_calibration_as_it_was(tmp_path):
    """A recording with one APS frame (no frame pair: nothing is measured) saved the defaults over the file given
    to --save-calibration, a good calibration among them, with its noise rates gone."""
    import numpy as np

    from edi_live.aedat4 import Aedat4Writer
    from edi_live.datatypes import EVENT_DTYPE, Frame

    rec = tmp_path / "one_frame.aedat4"
    events = np.zeros(2000, EVENT_DTYPE)
    events["t"] = 10_000 + np.arange(2000) * 10
    events["x"], events["y"] = np.arange(2000) % 346, np.arange(2000) % 260
    with Aedat4Writer(rec, 346, 260, camera_name=CAM.label) as w:
        w.write_events(events)
        w.write_frame(Frame(np.full((260, 346), 80, np.uint8), 20_000, 25_000))
    saved = tmp_path / "cam.json"
    calibration.save(calibration.Calibration(CAM.label, 346, 260, 0.31, 0.27, 4.5), saved)
    before = saved.read_bytes()
    run = _node("--replay", str(rec), "--speed", "0", "--no-publish", "--save-calibration", str(saved))
    errors = [line for line in run.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert run.returncode == 1 and len(errors) == 1, run.stderr
    assert "nothing to save" in errors[0] and str(saved) in errors[0] and "left as it was" in errors[0]
    assert saved.read_bytes() == before


def test_a_live_camera_picks_up_its_own_calibration(tmp_path):
    env = {"XDG_CONFIG_HOME": str(tmp_path)}
    args = ("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--duration", "1.5", "--no-publish")
    first = _node(*args, env=env)
    assert first.returncode == 0, first.stderr
    files = list((tmp_path / "edi-live" / "calibration").glob("*.json"))
    assert len(files) == 1 and "starting from the calibration" not in first.stderr
    second = _node(*args, env=env)
    assert second.returncode == 0 and f"starting from the calibration {files[0]}" in second.stderr, second.stderr


def test_a_live_cameras_own_file_of_another_sensor_set_up_is_ignored_with_a_warning(tmp_path):
    env = {"XDG_CONFIG_HOME": str(tmp_path)}
    args = ("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--duration", "1.0", "--no-publish")
    first = _node(*args, env=env)
    own, = (tmp_path / "edi-live" / "calibration").glob("*.json")
    cal = calibration.load(own)
    calibration.save(calibration.Calibration(cal.camera, 346, 260, 0.3, 0.3), own)  # another size, same serial
    second = _node(*args, env=env)
    assert first.returncode == 0 and second.returncode == 0, second.stderr
    assert "not using it" in second.stderr and "starting from the calibration" not in second.stderr
    assert calibration.load(own).width == cal.width, "the run saved its own calibration over the stale one"


# A live camera's own file, damaged by a hand edit, refused the camera with a usage error (exit 2) although no
# flag named the file: the camera could not be used until the user found and deleted it.
def test_a_live_cameras_own_damaged_file_is_ignored_with_a_warning_and_kept(tmp_path):
    env = {"XDG_CONFIG_HOME": str(tmp_path)}
    args = ("--device", "davis240", "--usb-backend", "drivers.emulator:backend", "--duration", "1.0", "--no-publish")
    first = _node(*args, env=env)
    own, = (tmp_path / "edi-live" / "calibration").glob("*.json")
    damaged = own.read_text().replace('"c_on"', '"c_on": 0.3,, "was"', 1)  # a typo: not JSON any more
    own.write_text(damaged)
    second = _node(*args, env=env)
    assert first.returncode == 0 and second.returncode == 0, second.stderr
    assert "not using it" in second.stderr and str(own) in second.stderr and "edi-live: error" not in second.stderr
    assert own.read_text() == damaged, "the run saved over the user's file"


def test_a_failed_save_leaves_no_temporary_file(tmp_path):
    target = tmp_path / "cam.json"
    target.mkdir()  # a folder where the file should go: the rename fails
    with pytest.raises(ConfigError, match="cannot write calibration"):
        calibration.save(calibration.Calibration("edi-live-sim", 48, 36, 0.2, 0.2), target)
    assert [p.name for p in tmp_path.iterdir()] == ["cam.json"]


def test_a_huge_file_given_as_calibration_is_refused_without_reading_it_all(tmp_path):
    # --calibration /dev/zero (or a recording given by mistake) was read whole: MemoryError or a hang
    big = tmp_path / "rec.aedat4"
    with big.open("wb") as fh:
        fh.truncate(calibration.MAX_FILE_BYTES + 1)  # sparse: no disk used
    with pytest.raises(ConfigError, match=f"calibration {big} is not a JSON file .larger than 64 MiB"):
        calibration.load(big)


def test_a_file_where_the_save_needs_a_folder_is_named_not_called_an_existing_calibration(tmp_path):
    """`--save-calibration rec.aedat4/cam.json` (a file where a folder should be) was refused with "(File exists)",
    as if the calibration existed and could not be replaced; the file in the way is named instead."""
    blocker = tmp_path / "rec.aedat4"
    blocker.write_bytes(b"a recording")
    target = blocker / "cams" / "cam.json"
    with pytest.raises(ConfigError) as info:
        calibration.check_can_save(target)
    message = str(info.value)
    assert str(target) in message and f"{blocker} is a file, not a folder" in message and "File exists" not in message
    assert blocker.read_bytes() == b"a recording"


def test_a_save_never_replaces_a_device_or_a_pipe(tmp_path):
    # the rename used to replace whatever was there: as root, --save-calibration /dev/full turned the device
    # into a JSON file
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    for check in (calibration.check_can_save,
                  lambda p: calibration.save(calibration.Calibration("edi-live-sim", 48, 36, 0.2, 0.2), p)):
        with pytest.raises(ConfigError, match="not a regular file"):
            check(fifo)
        assert fifo.is_fifo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe"]


def test_an_unwritable_save_calibration_fails_before_the_run(real_recordings, tmp_path):
    # it failed only after the whole run had been measured (a live session's calibration lost at the end)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    out = tmp_path / "sharp.aedat4"
    proc = _node("--replay", str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0", "--no-publish",
                 "--out", str(out), "--save-calibration", str(blocker / "cal.json"))
    errors = [line for line in proc.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert proc.returncode == 2 and len(errors) == 1 and "cannot write calibration" in errors[0], proc.stderr
    assert "frames out" not in proc.stderr and not out.exists(), "the run went ahead before the error"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_a_measured_black_level_stays_measured_through_the_stats_rounding():
    """The stats carry the black level to 2 decimals; a measured 10.125 DN that the run used as given must be
    saved as it was measured, not as a 10.12 DN starting value to be estimated again."""
    info = SourceInfo(width=48, height=36, name="edi-live-sim")
    start = calibration.Calibration(info.label, 48, 36, 0.2, 0.2, black_level=10.125, black_level_measured=True)
    cal = calibration.from_stats(info, {"c_on": 0.2, "c_off": 0.2, "black_level_dn": 10.12}, start=start)
    assert cal.black_level_measured and cal.black_level == 10.125
    replaced = calibration.from_stats(info, {"c_on": 0.2, "c_off": 0.2, "black_level_dn": 5.0}, start=start)
    assert not replaced.black_level_measured and replaced.black_level == 5.0


def test_a_full_disk_at_the_save_is_a_runtime_error_not_a_usage_error(tmp_path, monkeypatch):
    # ENOSPC from a full tmpfs was a ConfigError (exit 2, 'usage error'): where to write was checked before the run
    from pathlib import Path

    from edi_live.errors import OutputError

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    target = tmp_path / "cam.json"
    with pytest.raises(OutputError, match=f"cannot write calibration {target} .No space left") as info:
        calibration.save(calibration.Calibration("edi-live-sim", 48, 36, 0.2, 0.2), target)
    assert info.value.exit_code == 1
    assert list(tmp_path.iterdir()) == []


def test_a_service_account_without_a_home_folder_gets_a_warning_and_no_folder_is_made(tmp_path, real_recordings):
    # HOME=/nonexistent (a daemon account) made the end-of-run save create /nonexistent/.config/... as root
    # (and an empty HOME, /.config); it must not make a home that is not there
    home = tmp_path / "nonexistent"
    env = {k: v for k, v in os.environ.items() if k != "XDG_CONFIG_HOME"}
    proc = subprocess.run([sys.executable, "-m", "edi_live", "--device", "davis346", "--usb-backend",
                           "drivers.emulator:backend", "--emulate-from",
                           str(real_recordings["evlib_sample_davis346.aedat4"]), "--speed", "0", "--no-publish"],
                          cwd=REPO, capture_output=True, text=True, timeout=90,
                          env={**env, "PYTHONPATH": str(REPO), "HOME": str(home)})
    assert proc.returncode == 0, proc.stderr
    assert f"the home folder '{home}' does not exist" in proc.stderr and "edi-live: error" not in proc.stderr
    assert not home.exists()
    dark = _node("--device", "davis346", "--usb-backend", "drivers.emulator:backend", "--calibrate-dark", "2",
                 env={"HOME": str(home), "XDG_CONFIG_HOME": ""})
    assert dark.returncode == 2 and "--calibrate-dark: the home folder" in dark.stderr and not home.exists()
