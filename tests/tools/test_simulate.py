"""The simulator's command line (tools/simulate.py): files that dv-processing reads back, options, errors, help."""

from __future__ import annotations

import numpy as np
import pytest

from edi_live.simulation import EFFECTS, load_ground_truth, preset, simulate
from tools import simulate as sim_mod


def test_cli_writes_aedat4_that_dv_processing_reads_back(tmp_path):
    import dv_processing as dv  # test extra: the independent oracle for the file we write
    out = tmp_path / "sim.aedat4"
    rc = sim_mod.main([str(out), "--preset", "translate", "--duration-s", "0.25", "--seed", "5",
                       "--noise-rate-hz", "1", "--imu"])
    assert rc == 0 and out.is_file() and out.with_suffix(".npz").is_file()
    s = simulate(preset("translate", duration_s=0.25, seed=5, noise_rate_hz=1.0, imu=True))
    rec = dv.io.MonoCameraRecording(str(out))
    assert tuple(rec.getEventResolution()) == (240, 180)
    n, ts = 0, []
    while True:
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        n += batch.size()
        if batch.size():
            ts.append(batch.timestamps())
    assert n == s.events.size
    np.testing.assert_array_equal(np.concatenate(ts), s.events["t"])
    frames = []
    while (fr := rec.getNextFrame()) is not None:
        frames.append(fr)
    assert len(frames) == len(s.frames)
    np.testing.assert_array_equal(np.asarray(frames[1].image).reshape(180, 240), s.frames[1].image)
    assert frames[1].exposure.total_seconds() * 1e6 == pytest.approx(s.config.exposure_us, abs=1)


def test_cli_rejects_bad_options_with_exit_code_2(tmp_path, capsys):
    assert sim_mod.main([str(tmp_path / "x.aedat4"), "--texture", "nope"]) == 2
    assert "unknown texture" in capsys.readouterr().err
    assert sim_mod.main([str(tmp_path / "x.aedat4"), "--exposure-us", "90000", "--frame-interval-us", "50000"]) == 2
    assert not (tmp_path / "x.aedat4").exists()


def test_cli_bad_output_path_is_one_line_before_simulating(tmp_path, capsys):
    assert sim_mod.main([str(tmp_path / "missing" / "x.aedat4"), "--duration-s", "0.05"]) == 2
    assert sim_mod.main([str(tmp_path), "--duration-s", "0.05"]) == 2
    err = capsys.readouterr().err
    assert "its folder does not exist" in err and "it is a directory" in err and "Traceback" not in err


@pytest.mark.parametrize("args,fragment", [
    (["--duration-s", "-1"], "duration_s must be > 0"),
    (["--duration-s", "nan"], "duration_s must be > 0"),
    (["--noise-rate-hz", "-2"], "noise_rate_hz must be >= 0"),
    (["--hot-pixels", "-1"], "hot_pixels must be >= 0"),
])
def test_cli_negative_rates_and_durations_name_the_option(tmp_path, capsys, args, fragment):
    assert sim_mod.main([str(tmp_path / "x.aedat4"), *args]) == 2
    assert fragment in capsys.readouterr().err
    assert not (tmp_path / "x.aedat4").exists()


def test_cli_help_lists_the_defaults_and_presets(capsys):
    with pytest.raises(SystemExit) as info:
        sim_mod.main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert f"c_on={sim_mod.SceneConfig().c_on}" in out and "exposure_us=" in out and "examples:" in out
    assert all(f"  {name}: " in out for name in sim_mod.PRESETS)


def test_cli_switches_effects_on_alone_or_all_and_the_help_lists_them(tmp_path, capsys):
    out = tmp_path / "lamp.aedat4"
    assert sim_mod.main([str(out), "--preset", "translate", "--duration-s", "0.1", "--effect", "flicker",
                         "--flicker-hz", "120", "--effect", "black_level"]) == 0
    cfg = load_ground_truth(out.with_suffix(".npz"))["config"]
    assert cfg["flicker_hz"] == 120.0 and cfg["aps_offset_dn"] == 10.0 and cfg["event_offset_us"] == 0
    assert sim_mod.main([str(out), "--preset", "realistic", "--duration-s", "0.1"]) == 0
    assert set(load_ground_truth(out.with_suffix(".npz"))["config"]["effects"]) == set(EFFECTS)
    with pytest.raises(SystemExit) as info:
        sim_mod.main([str(out), "--effect", "rain"])
    assert info.value.code == 2
    capsys.readouterr()
    with pytest.raises(SystemExit):
        sim_mod.main(["--help"])
    help_text = capsys.readouterr().out
    assert all(f"  {name}: " in help_text for name in EFFECTS) and "Source:" in help_text
    assert preset("realistic").effects == tuple(EFFECTS)
    assert simulate(preset("realistic", width=32, height=24, duration_s=0.06)).events.size > 0


# Each of these ended in a traceback (inf: OverflowError), wrote a recording with c=nan (only noise events, no
# scene), or ran for hours with no output before the first byte (a 1e12 px/s scene: a million 1 µs render steps
# per second; 1e8 latent frames: a Python loop over 3e9 ground-truth times; a 1e7 s recording: terabytes of
# APS accumulators). Run as a subprocess, so that a run that does not stop fails the test by its timeout.
@pytest.mark.parametrize("args,fragment", [
    (["--duration-s", "inf"], "duration_s must be a finite number"),
    (["--c", "nan"], "contrast thresholds must be positive numbers"),
    (["--c-off", "inf"], "contrast thresholds must be positive numbers"),
    (["--rotation-deg-s", "inf"], "rotation_deg_s must be a finite number"),
    (["--velocity", "1e12,0"], "faster than the simulator renders"),
    (["--zoom-per-s", "0.8", "--duration-s", "1000", "--no-ground-truth"], "faster than the simulator renders"),
    (["--latent-per-interval", "100000000"], "ground-truth images"),
    (["--duration-s", "1e7", "--velocity", "0,0", "--rotation-deg-s", "0", "--no-ground-truth"], "GiB of memory"),
    (["--latent-per-interval", "-1"], "latent_per_interval must be >= 0"),
])
def test_cli_impossible_sizes_are_refused_at_once_naming_the_option(tmp_path, args, fragment):
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "x.aedat4"
    proc = subprocess.run([sys.executable, "-m", "tools.simulate", str(out), *args], capture_output=True, text=True,
                          timeout=60, cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 2, proc.stderr
    assert fragment in proc.stderr and "Traceback" not in proc.stderr and len(proc.stderr.splitlines()) == 1
    assert not out.exists()


# The ground truth is written after the recording: an OUT.npz that was a folder, or a full disk, ended the run
# with an IsADirectoryError/OSError traceback after the whole simulation (and a recording named .npz was
# overwritten by its own ground truth).
def test_cli_a_ground_truth_that_cannot_be_written_is_one_line(tmp_path, capsys):
    (tmp_path / "folder.npz").mkdir()
    assert sim_mod.main([str(tmp_path / "folder.aedat4"), "--duration-s", "0.05"]) == 2
    assert sim_mod.main([str(tmp_path / "same.npz"), "--duration-s", "0.05"]) == 2
    err = capsys.readouterr().err
    assert "it is a directory" in err and "would replace the recording" in err and "Traceback" not in err
    assert not (tmp_path / "folder.aedat4").exists() and not (tmp_path / "same.npz").exists()


def test_cli_a_full_disk_for_the_ground_truth_keeps_the_recording(tmp_path, capsys):
    import os

    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full (a device that is always full)")
    (tmp_path / "full.npz").symlink_to("/dev/full")
    assert sim_mod.main([str(tmp_path / "full.aedat4"), "--duration-s", "0.1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot write the ground truth" in err and "No space left" in err
    import dv_processing as dv

    reader = dv.io.MonoCameraRecording(str(tmp_path / "full.aedat4"))
    assert reader.getNextEventBatch() is not None  # the recording itself is complete and readable
