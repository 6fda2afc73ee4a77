"""The black level measured on dark frames (--calibrate-dark): the measurement, the file it writes, and a later run
that uses it as given and keeps it measured."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from edi_live import calibration
from edi_live.aedat4.writer import Aedat4Writer
from edi_live.dark_calibration import measure_black_level
from edi_live.datatypes import EVENT_DTYPE, Frame
from edi_live.errors import ConfigError, EdiLiveError
from edi_live.simulation import preset, simulate, with_effects, write_aedat4

REPO = Path(__file__).resolve().parents[2]


def _dark_images(rng, black: float, n: int = 8, shape=(36, 48), noise: float = 1.0, hot: float = 0.005):
    images = []
    for _ in range(n):
        img = black + rng.normal(0.0, noise, shape)
        img[rng.random(shape) < hot] = 200.0  # hot pixels
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return images


@pytest.mark.parametrize("black", [0.0, 4.0, 10.0, 23.0])
def test_the_black_level_of_dark_frames_is_found_within_half_a_dn(rng, black):
    result = measure_black_level(_dark_images(rng, black))
    assert abs(result.black_level - black) <= 0.5
    assert result.frames == 8 and result.bright_fraction < 0.02
    if black >= 4:  # (at 0 DN half the noise is clipped away)
        assert 0.7 <= result.noise_dn <= 1.3


def test_16_bit_dark_frames_are_measured_on_the_8_bit_scale(rng):
    images = [(img.astype(np.uint16) * 257) for img in _dark_images(rng, 12.0)]
    assert abs(measure_black_level(images).black_level - 12.0) <= 0.5


def test_frames_that_are_not_dark_are_refused_saying_what_was_seen(rng):
    lit = [np.full((36, 48), 120, np.uint8) for _ in range(4)]
    for img in lit:
        img[:, :24] = 10  # half the frame dark, half lit: a scene, not a covered lens
    with pytest.raises(ConfigError, match="not dark .*cover the lens"):
        measure_black_level(lit)
    with pytest.raises(ConfigError, match="no APS frame"):
        measure_black_level([])


def _write_dark_recording(path: Path, rng, black: float, n: int = 6, width: int = 48, height: int = 36) -> None:
    """A covered camera: dark APS frames every 20 ms and a trickle of noise events, as the simulator's camera."""
    with Aedat4Writer(path, width, height, events=True, frames=True, camera_name="edi-live-sim") as writer:
        for k, image in enumerate(_dark_images(rng, black, n, (height, width))):
            ev = np.zeros(5, EVENT_DTYPE)
            ev["t"] = np.sort(rng.integers(k * 20_000, k * 20_000 + 10_000, 5))
            ev["x"], ev["y"] = rng.integers(0, width, 5), rng.integers(0, height, 5)
            writer.write_events(ev)
            writer.write_frame(Frame(image=image, exposure_start_us=k * 20_000, exposure_end_us=k * 20_000 + 10_000))


def _node(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "edi_live", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(REPO)})


def test_calibrate_dark_writes_the_measured_black_level_and_keeps_the_rest_of_the_cameras_file(tmp_path, rng):
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 10.0)
    saved = tmp_path / "cam.json"
    done = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "5", "--save-calibration", str(saved))
    assert done.returncode == 0, done.stderr
    cal = calibration.load(saved)
    assert abs(cal.black_level - 10.0) <= 0.5 and cal.black_level_measured
    assert (cal.camera, cal.width, cal.height) == ("edi-live-sim", 48, 36)
    assert f"black level {cal.black_level:g} DN" in done.stderr and str(saved) in done.stderr
    calibration.save(dataclasses.replace(cal, c_on=0.31, c_off=0.27, clock_offset_us=900), saved)
    again = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "3", "--save-calibration", str(saved))
    kept = calibration.load(saved)
    assert again.returncode == 0 and (kept.c_on, kept.c_off, kept.clock_offset_us) == (0.31, 0.27, 900)


def test_calibrate_dark_without_a_file_to_write_or_on_a_lit_scene_is_one_line(tmp_path, rng):
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 10.0)
    nowhere = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "5")
    lines = [line for line in nowhere.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert nowhere.returncode == 2 and len(lines) == 1 and "--save-calibration" in lines[0], nowhere.stderr
    lit = tmp_path / "lit.aedat4"
    sim = simulate(preset("translate", texture="camera", width=48, height=36, duration_s=0.1, seed=3))
    write_aedat4(sim, lit)
    refused = _node("--replay", str(lit), "--speed", "0", "--calibrate-dark", "3", "--save-calibration",
                    str(tmp_path / "x.json"))
    lines = [line for line in refused.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert refused.returncode == 2 and len(lines) == 1 and "not dark" in lines[0], refused.stderr
    assert not (tmp_path / "x.json").exists()


def test_a_measured_black_level_is_used_as_given_and_stays_measured(tmp_path, rng):
    """A scene without dark pixels (blocks) cannot show the stream its black level: started from the dark frames'
    measurement, the node uses it from the first frame, never replaces it, and saves it as measured again."""
    cfg = with_effects(preset("translate", texture="blocks", width=96, height=72, duration_s=0.3,
                              velocity_px_s=(200.0, 40.0), seed=7), "black_level")
    scene = tmp_path / "blocks.aedat4"
    write_aedat4(simulate(cfg), scene)
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, float(cfg.aps_offset_dn), width=96, height=72)
    cal_file = tmp_path / "cam.json"
    assert _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "4", "--save-calibration",
                 str(cal_file)).returncode == 0
    measured = calibration.load(cal_file).black_level
    after = tmp_path / "after.json"
    run = _node("--replay", str(scene), "--speed", "0", "--no-publish", "--calibration", str(cal_file),
                "--save-calibration", str(after))
    assert run.returncode == 0, run.stderr
    assert f"black level {measured:g} DN," in run.stderr, run.stderr  # given: neither estimated nor a start value
    saved = calibration.load(after)
    assert saved.black_level == measured and saved.black_level_measured
    # one run with a --black-level flag uses the flag's value, and the file keeps its measurement
    flagged = _node("--replay", str(scene), "--speed", "0", "--no-publish", "--calibration", str(after),
                    "--black-level", "3", "--save-calibration", str(after))
    assert flagged.returncode == 0 and "black level 3 DN," in flagged.stderr, flagged.stderr
    kept = calibration.load(after)
    assert kept.black_level == measured and kept.black_level_measured


def test_a_live_camera_measures_into_its_own_file_and_a_lit_one_is_refused(tmp_path):
    """Without --save-calibration a live camera writes its own calibration file; the emulated camera looks at a
    lit scene, so the measurement is refused and no file is written."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "XDG_CONFIG_HOME": str(tmp_path)}
    done = subprocess.run([sys.executable, "-m", "edi_live", "--device", "davis240", "--usb-backend",
                           "drivers.emulator:backend", "--calibrate-dark", "3"], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env=env)
    lines = [line for line in done.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert done.returncode == 2 and len(lines) == 1 and "not dark" in lines[0], done.stderr
    assert not list(tmp_path.rglob("*.json"))


# --- review3: failing-test demonstrations -------------------------------------------------------------------------

def test_a_dim_lit_scene_is_not_taken_for_a_black_level():
    """An uncovered lens in a dim room: the blocks scene at a tenth of its brightness has no pixel 15 DN above its
    median, yet it is a scene, not sensor noise (neighbouring pixels agree). Its 'black level' would be used as
    given for ever, so it must be refused."""
    sim = simulate(preset("translate", texture="blocks", width=96, height=72, duration_s=0.1, seed=3))
    dim = [np.rint(frame.image * 0.1).astype(np.uint8) for frame in sim.frames]
    with pytest.raises(ConfigError, match="not dark"):
        measure_black_level(dim)


def test_dark_frames_with_column_fixed_pattern_noise_and_hot_pixels_are_accepted(rng):
    """A DAVIS346 dark frame: column offsets (2 DN), read noise and hot pixels; the darkness check must not take
    the column pattern for a scene."""
    columns = rng.normal(0.0, 2.0, 48)
    images = [np.clip(np.rint(img + columns[None, :]), 0, 255).astype(np.uint8) for img in _dark_images(rng, 10.0)]
    assert abs(measure_black_level(images).black_level - 10.0) <= 1.0


def test_an_existing_calibration_that_cannot_be_merged_is_refused_and_left_alone(tmp_path, rng):
    """--save-calibration naming a corrupt file, or another camera's, must not overwrite it (one line, exit 2)."""
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 10.0)
    corrupt = tmp_path / "corrupt.json"
    corrupt.write_text('{"format": "edi-live calibration", "version": 1, "camera": ')
    other = tmp_path / "other.json"
    calibration.save(calibration.Calibration("DAVIS346_00000391", 346, 260, 0.31, 0.27, clock_offset_us=900), other)
    for target in (corrupt, other):
        before = target.read_text()
        done = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "3", "--save-calibration",
                     str(target))
        lines = [line for line in done.stderr.splitlines() if line.startswith("edi-live: error:")]
        assert done.returncode == 2 and len(lines) == 1 and str(target) in lines[0], done.stderr
        assert target.read_text() == before


class _StopAfter:
    """cli.StopSignals stand-in: keeps what it stops, for the test source to stop mid-read (a Ctrl-C)."""

    def __init__(self) -> None:
        self.target = None

    def attach(self, target) -> None:
        self.target = target


class _FrameSource:
    """A replay-like source of APS frames for calibrate_dark; `before(k)` runs before frame k is handed over."""

    def __init__(self, images, before=None):
        from edi_live.datatypes import SourceInfo

        self.info = SourceInfo(width=48, height=36, name="edi-live-sim", kind="replay")
        self.images, self.before, self.iterated = images, before, False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def __iter__(self):
        from edi_live.datatypes import Packet

        self.iterated = True
        for k, image in enumerate(self.images):
            if self.before is not None:
                self.before(k)
            yield Packet(frames=[Frame(image=image, exposure_start_us=k * 20_000, exposure_end_us=k * 20_000 + 10_000)])


def test_a_signal_before_n_frames_writes_nothing(tmp_path, rng):
    """Ctrl-C during --calibrate-dark 6 after 2 frames: the camera's 'measured' black level must not come from
    fewer frames than asked; nothing is written and the error says it was stopped."""
    from edi_live.dark_calibration import calibrate_dark

    signals = _StopAfter()

    def stop_at_the_third(k):
        if k == 2:
            signals.target.stop()

    target = tmp_path / "cam.json"
    with pytest.raises(EdiLiveError, match="stopped"):
        calibrate_dark(_FrameSource(_dark_images(rng, 10.0, n=6), stop_at_the_third), 6, target, signals)
    assert not target.exists()


def test_an_unwritable_target_is_refused_before_any_frame_is_read(tmp_path):
    # it was found only at the end: a live camera's --calibrate-dark 1000 with the lens covered, then the error
    from edi_live.dark_calibration import calibrate_dark

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    source = _FrameSource([])
    with pytest.raises(ConfigError, match="cannot write calibration"):
        calibrate_dark(source, 3, blocker / "cam.json")
    assert not source.iterated


def test_calibrate_dark_with_loop_on_a_recording_without_frames_ends(tmp_path):
    """--loop would replay a recording without APS frames for ever; each recorded frame is measured once."""
    events_only = tmp_path / "events.aedat4"
    with Aedat4Writer(events_only, 48, 36, events=True, frames=False, camera_name="edi-live-sim") as writer:
        ev = np.zeros(5, EVENT_DTYPE)
        ev["t"] = np.arange(5) * 1000
        writer.write_events(ev)
    done = _node("--replay", str(events_only), "--speed", "0", "--loop", "--calibrate-dark", "3",
                 "--save-calibration", str(tmp_path / "cam.json"))
    lines = [line for line in done.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert done.returncode == 2 and len(lines) == 1 and "no APS frame" in lines[0], done.stderr


def test_many_dark_frames_are_measured_on_an_even_sample_of_them(tmp_path, rng):
    """--calibrate-dark 300 on a recording of 300 dark frames keeps at most 64 of them (memory stays bounded: a
    thousand full frames took 1.3 GB) and still finds the level."""
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 7.0, n=300)
    saved = tmp_path / "cam.json"
    done = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "300", "--save-calibration", str(saved))
    assert done.returncode == 0, done.stderr
    assert abs(calibration.load(saved).black_level - 7.0) <= 0.5
    measured = int(re.search(r"(\d+) dark frames", done.stderr).group(1))
    assert 32 < measured <= 64, done.stderr  # an even sample: more than half the cap


def test_a_recording_shorter_than_asked_is_measured_on_all_its_frames(tmp_path, rng):
    """--calibrate-dark 1000 on 4 dark frames measures the 4 (it took only the first: one in every 16 of the
    1000 asked for), and says the input ended early."""
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 7.0, n=4)
    saved = tmp_path / "cam.json"
    done = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "1000", "--save-calibration", str(saved))
    assert done.returncode == 0, done.stderr
    assert "ended after 4 of 1000" in done.stderr and "4 dark frames" in done.stderr, done.stderr


def test_outputs_that_calibrate_dark_does_not_write_are_said_to_be_ignored(tmp_path, rng):
    # --record raw.aedat4 beside --calibrate-dark wrote nothing and said nothing
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 5.0, n=3)
    done = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "3", "--save-calibration",
                 str(tmp_path / "cam.json"), "--out", str(tmp_path / "sharp.aedat4"), "--record",
                 str(tmp_path / "raw.aedat4"))
    assert done.returncode == 0, done.stderr
    assert "ignored with --calibrate-dark: --out, --record" in done.stderr, done.stderr
    assert not (tmp_path / "sharp.aedat4").exists() and not (tmp_path / "raw.aedat4").exists()


def test_a_written_calibration_with_stderr_into_a_closed_pipe_still_exits_0(tmp_path, rng):
    # its one result line went to stderr with print(): a reader gone ('2>&1 | head -0', a stopped log shipper)
    # turned the finished, written calibration into an internal BrokenPipeError (exit 1)
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 10.0)
    saved = tmp_path / "cam.json"
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run([sys.executable, "-m", "edi_live", "--replay", str(dark), "--speed", "0",
                               "--calibrate-dark", "5", "--save-calibration", str(saved)], cwd=REPO,
                              stdout=subprocess.DEVNULL, stderr=write_end, timeout=60,
                              env={**os.environ, "PYTHONPATH": str(REPO)})
    finally:
        os.close(write_end)
    assert proc.returncode == 0
    assert abs(calibration.load(saved).black_level - 10.0) <= 0.5


def test_a_pipe_as_the_target_is_refused_as_not_a_file_without_reading_it(tmp_path, rng):
    # the target was first read as an existing calibration: a FIFO waited 5 s for a writer and was then called a
    # pipe nothing wrote to (/dev/full: 'not a JSON file, larger than 64 MiB'), where a run says 'not a regular file'
    dark = tmp_path / "dark.aedat4"
    _write_dark_recording(dark, rng, 10.0)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    proc = _node("--replay", str(dark), "--speed", "0", "--calibrate-dark", "3", "--save-calibration", str(fifo))
    lines = [line for line in proc.stderr.splitlines() if line.startswith("edi-live: error:")]
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "not a regular file" in lines[0] and "nothing wrote" not in lines[0]
    assert fifo.is_fifo()
