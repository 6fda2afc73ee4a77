"""The APS black level measured on dark frames, the way it is done for any CMOS camera: cover the lens, take a few
frames, and the value they sit at is the black level (`edi-live --calibrate-dark N`).

Why a measurement: the node estimates the black level from the stream, but only dark pixels carry it
(docs/calibration.md: a scene without any pixel near black, such as the realistic benchmark's blocks, leaves it
unidentified, and a scene with few dark pixels finds it late and low). It belongs to the camera and its bias
settings, not to the scene, so a measured value is saved in the camera's calibration file and used as given from
then on (`black_level_measured`).

This module owns:
- `measure_black_level`: plain function on frames (the median of every pixel, the spread, a darkness check);
- `calibrate_dark`: reads N APS frames from a source, measures them, and writes the black level into the camera's
  calibration file (merged into the file there, which must be this camera's and readable: another camera's or a
  corrupt file is refused, not overwritten; without a file, a new one with the node's starting values for
  everything else).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from edi_live import calibration
from edi_live.black_level_policy import MAX_BLACK_DN
from edi_live.datatypes import SourceInfo
from edi_live.edi import blurry_to_float
from edi_live.errors import ConfigError, EdiLiveError
from edi_live.source import stop_from_another_thread

log = logging.getLogger(__name__)

BRIGHT_DN = 15.0  # a pixel this far above the black level is lit (or hot)
MAX_BRIGHT_FRACTION = 0.02  # more lit pixels than this: the frames are not dark
# Neighbouring pixels of a scene agree (0.94-0.97 on the three real DAVIS346 recordings, also dimmed to a tenth,
# where no pixel is 15 DN above the median); dark frames' read noise does not (< 0.1 with 2 DN column offsets)
MAX_NEIGHBOUR_CORRELATION = 0.5
MAX_MEASURED_FRAMES = 64  # more frames add nothing to a median over millions of pixels (1000 took 1.3 GB)


@dataclass(frozen=True)
class DarkFrames:
    black_level: float  # 8-bit DN: the median of every pixel of every frame
    noise_dn: float  # spread of the pixels within 5 DN of it (hot and lit pixels left out; includes rounding)
    bright_fraction: float  # pixels more than BRIGHT_DN above it
    frames: int


def measure_black_level(images: Sequence[np.ndarray]) -> DarkFrames:
    """The black level of dark APS frames (uint8 or uint16, on the 8-bit scale the node works on). Raises
    ConfigError, saying what was seen, when the frames are not dark: more than 2 % of the pixels lit, or a level
    above what the node accepts as a black level."""
    if not images:
        raise ConfigError("no APS frame to measure the black level on (does the input have APS frames?)")
    frames = [blurry_to_float(np.asarray(image))[0] for image in images]  # the 8-bit scale, once per frame
    values = np.concatenate([frame.reshape(-1) for frame in frames])
    black = float(np.median(values))
    near = values[np.abs(values - black) <= BRIGHT_DN / 3]
    noise = float(np.std(near)) if near.size else 0.0
    bright = float(np.mean(values > black + BRIGHT_DN))
    result = DarkFrames(round(black, 2), round(noise, 2), bright, len(images))
    if bright > MAX_BRIGHT_FRACTION or black >= MAX_BLACK_DN:
        p99 = float(np.percentile(values, 99))
        raise ConfigError(f"the APS frames are not dark (median {black:.1f} DN, 99th percentile {p99:.1f} DN, "
                          f"{100 * bright:.1f} % of the pixels more than {BRIGHT_DN:g} DN above the median, over "
                          f"{len(images)} frames): cover the lens and run --calibrate-dark again")
    agreement = _neighbour_correlation(frames, black)
    if agreement > MAX_NEIGHBOUR_CORRELATION:
        raise ConfigError(f"the APS frames are not dark (median {black:.1f} DN, but neighbouring pixels agree like "
                          f"a scene's: correlation {agreement:.2f}, over {len(images)} frames): cover the lens and "
                          f"run --calibrate-dark again")
    return result


def _neighbour_correlation(frames: Sequence[np.ndarray], black: float) -> float:
    """The lesser of the horizontal and the vertical correlation of adjacent pixels' deviations from `black`
    (hot pixels clipped), median over the frames (on the 8-bit scale): column (or row) offsets raise only one of
    them, a scene both."""
    per_frame = []
    for frame in frames:
        d = np.clip(frame - black, -BRIGHT_DN, BRIGHT_DN)
        pairs = ((d[:, :-1], d[:, 1:]), (d[:-1], d[1:]))
        per_frame.append(min(_correlation(a, b) for a, b in pairs))
    return float(np.median(per_frame))


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = (np.asarray(x, np.float64).reshape(-1) for x in (a, b))
    a, b = a - a.mean(), b - b.mean()
    scale = float(np.sqrt(np.dot(a, a) * np.dot(b, b)))
    return float(np.dot(a, b)) / scale if scale > 0 else 0.0


class _Stop:
    """What the command line's signal handler stops (StopSignals.attach)."""

    def __init__(self, source: Any) -> None:
        self.event = threading.Event()
        self.source = source

    def stop(self) -> None:
        self.event.set()
        stop_source = getattr(self.source, "stop", None)  # (a Source has one; a plain iterable of packets not)
        if stop_source is not None:  # also ends a wait inside the source (a camera gone while starting, --reconnect)
            stop_from_another_thread(stop_source)


def calibrate_dark(source: Any, n_frames: int, target: Path | None, signals: Any = None) -> tuple[DarkFrames, Path]:
    """Read `n_frames` APS frames from `source` (a driver, not yet opened), measure their black level and write it
    into the calibration file `target` (None: a live camera's own file). The end of the input before n frames
    measures what was read; a signal (through `signals`, cli.StopSignals) before n frames writes nothing, since a
    measured black level is never re-estimated. Returns (the measurement, the file written)."""
    if n_frames < 1:
        raise ConfigError(f"--calibrate-dark needs a number of APS frames of at least 1 (got {n_frames})")
    stop = _Stop(source)
    if signals is not None:
        signals.attach(stop)
    images: list[np.ndarray] = []
    read = 0
    stride = 1  # every frame, until more than MAX_MEASURED_FRAMES are kept: then every other, and so on
    with source:
        info = source.info
        if target is None:
            if info.kind not in ("usb", "emulator"):
                raise ConfigError("--calibrate-dark needs --save-calibration FILE to write to (a live camera writes "
                                  "its own calibration file)")
            if (problem := calibration.missing_home()) is not None:
                raise ConfigError(f"--calibrate-dark: {problem}")
            target = calibration.default_path(info)
        calibration.check_can_save(target)  # a place it cannot be written to (a device: not read as a file)
        existing_calibration(info, Path(target))  # and a file that cannot take the value: said before the frames
        for packet in source:
            if stop.event.is_set() or read >= n_frames:
                break
            for frame in packet.frames if packet is not None else ():
                if read < n_frames and read % stride == 0:
                    images.append(np.array(frame.image))  # a copy: a decoder may reuse its buffer
                    if len(images) > MAX_MEASURED_FRAMES:  # an even sample of what was read, however far it goes
                        images, stride = images[::2], 2 * stride
                read += 1
    if stop.event.is_set() and read < n_frames:
        raise EdiLiveError(f"--calibrate-dark stopped after {read} of {n_frames} APS frames; nothing written")
    if read < n_frames:
        log.warning("the input ended after %d of %d APS frames; measuring those", read, n_frames)
    result = measure_black_level(images)
    save_black_level(info, result.black_level, Path(target))
    return result, Path(target)


def existing_calibration(info: SourceInfo, target: Path) -> calibration.Calibration | None:
    """This camera's calibration at `target`, or None when there is no file. A file that cannot be read, or that
    belongs to another camera, is a ConfigError: it is not overwritten."""
    if not target.exists():
        return None
    try:
        cal = calibration.load(target)
    except ConfigError as exc:
        raise ConfigError(f"{exc}; --calibrate-dark does not overwrite it: move it away or name another "
                          f"--save-calibration file") from None
    if (cal.camera, cal.width, cal.height) != (info.label, info.width, info.height):
        raise ConfigError(f"calibration {target} is for {cal.camera} ({cal.width}x{cal.height}), not this camera "
                          f"{info.label} ({info.width}x{info.height}); --calibrate-dark does not overwrite it: move "
                          f"it away or name another --save-calibration file")
    return cal


def save_black_level(info: SourceInfo, black_level: float, target: Path) -> calibration.Calibration:
    """Write a measured black level into the calibration at `target`, keeping that file's other values (it must
    be this camera's: existing_calibration); without a file, a new one starts from the node's defaults (c 0.2,
    no clock offset)."""
    cal = existing_calibration(info, target)
    if cal is None:
        cal = calibration.Calibration(info.label, info.width, info.height, 0.2, 0.2)
    cal = dataclasses.replace(cal, black_level=float(black_level), black_level_measured=True, saved="")
    calibration.save(cal, target)
    return cal
