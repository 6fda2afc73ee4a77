"""Saved camera calibrations: what the node learned about one camera (c_on, c_off, the APS black level, the event
clock offset, each pixel's ON and OFF noise rate), stored as a JSON file keyed by camera model, serial and sensor
size, so that the next run starts from it.

The per-pixel noise rates are arrays: they go into the same JSON, under "noise", as three (H, W) row-major float16
little-endian arrays (ON Hz, OFF Hz, and the still seconds each pixel was watched, which weights the saved rate
when a run starts from it), each zlib-compressed and base64-encoded (at most ~0.7 MB for a DAVIS346; 43 kB after
emlb's 0.5 s). float16 keeps three significant digits, far below the estimate's own Poisson error. A file without
"noise" is as valid as before.

`--calibration FILE` loads one, `--save-calibration FILE` writes the values in use at the end of a run. A live
camera (USB) picks up its own without flags: it is loaded from, and saved to, `calibration_dir()/LABEL.json`
(LABEL is the camera name and serial, e.g. DAVIS346_00000391). A calibration of another camera or sensor size is
refused with one line (a live camera's own file of another size, or damaged, is skipped with a warning: no flag
named it). Loaded values are starting points: c, the black level and the clock offset are in use from the first
frame and still estimated from the stream, so that a value a short or unsuitable first run got wrong is
corrected (and saved corrected) rather than kept for ever; a black level or offset given on the command line wins
over the file's. A black level measured on dark frames (`--calibrate-dark`, edi_live.dark_calibration) is used
as given, not estimated again. The APS response cannot be estimated, so a saved one is used as it is; a black level
or offset beyond what the estimators search (black_level_policy.MAX_BLACK_DN, clock_offset_policy.MAX_OFFSET_US) is
kept.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import dataclasses
import json
import logging
import math
import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from edi_live.config import APS_GAMMA_RANGE, BLACK_LEVEL_END, C_RANGE, CLOCK_OFFSET_MAX_US, EdiConfig
from edi_live.checks import finite_number
from edi_live.config_file import read_limited
from edi_live.datatypes import SourceInfo
from edi_live.errors import ConfigError, OutputError
from edi_live.pixel_noise import NoiseRates

log = logging.getLogger(__name__)

FORMAT = "edi-live calibration"
VERSION = 1


@dataclass(frozen=True)
class Calibration:
    camera: str  # SourceInfo.label: name and serial
    width: int
    height: int
    c_on: float
    c_off: float
    black_level: float = 0.0  # 8-bit DN
    clock_offset_us: int = 0  # events arrive this much later than the APS exposure
    aps_gamma: float = 1.0  # APS response exponent
    saved: str = ""  # UTC time of saving, for the person reading the file
    black_level_measured: bool = False  # on dark frames (--calibrate-dark): used as given, never re-estimated
    noise: NoiseRates | None = field(default=None, compare=False, repr=False)  # per-pixel noise rates

    def check_for(self, info: SourceInfo, path: Path | str) -> None:
        """ConfigError unless this calibration belongs to the camera `info` describes."""
        if (self.camera, self.width, self.height) != (info.label, info.width, info.height):
            raise ConfigError(f"calibration {path} is for {self.camera} ({self.width}x{self.height}), but this camera "
                              f"is {info.label} ({info.width}x{info.height}); leave --calibration out or save one "
                              f"for this camera with --save-calibration")


def calibration_dir() -> Path:
    """Where live cameras keep their calibrations: $XDG_CONFIG_HOME/edi-live/calibration (~/.config/...)."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "edi-live" / "calibration"


def default_path(info: SourceInfo) -> Path:
    return calibration_dir() / f"{info.label}.json"


def missing_home() -> str | None:
    """Why a live camera's own file cannot be kept (None: it can): the home folder it would go under does not
    exist. A service account's HOME=/nonexistent (Debian's convention for daemons) or an empty HOME ('/') made
    the save at the end create /nonexistent/.config or /.config when run as root, and fail otherwise."""
    if os.environ.get("XDG_CONFIG_HOME"):
        return None
    home = os.path.expanduser("~")
    if home != "/" and os.path.isabs(home) and os.path.isdir(home):
        return None
    which = "HOME is empty or '/'" if home == "/" else f"the home folder {home!r} does not exist"
    return (f"{which}, so this camera's own calibration is not kept between runs (set XDG_CONFIG_HOME or HOME, or "
            f"give --save-calibration FILE)")


def _own_target(info: SourceInfo) -> Path | None:
    problem = missing_home()
    if problem is not None:
        log.warning("%s", problem)
        return None
    return default_path(info)


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# what load() accepts, per field: (field, what it must be, check); a refusal names the fields that broke their rule
_FIELD_RULES: tuple[tuple[str, str, Callable[[Any], bool]], ...] = (
    ("camera", "text", lambda v: isinstance(v, str)),
    ("width", "a positive integer", lambda v: _integer(v) and v > 0),
    ("height", "a positive integer", lambda v: _integer(v) and v > 0),
    ("c_on", f"a contrast threshold in [{C_RANGE[0]:g}, {C_RANGE[1]:g}]",
     lambda v: finite_number(v) and C_RANGE[0] <= v <= C_RANGE[1]),
    ("c_off", f"a contrast threshold in [{C_RANGE[0]:g}, {C_RANGE[1]:g}]",
     lambda v: finite_number(v) and C_RANGE[0] <= v <= C_RANGE[1]),
    ("black_level", f"DN in [0, {BLACK_LEVEL_END})", lambda v: finite_number(v) and 0 <= v < BLACK_LEVEL_END),
    ("clock_offset_us", f"an integer of µs within ±{CLOCK_OFFSET_MAX_US}",
     lambda v: _integer(v) and abs(v) <= CLOCK_OFFSET_MAX_US),
    ("aps_gamma", f"an exponent in [{APS_GAMMA_RANGE[0]:g}, {APS_GAMMA_RANGE[1]:g}]",
     lambda v: finite_number(v) and APS_GAMMA_RANGE[0] <= v <= APS_GAMMA_RANGE[1]),
    ("black_level_measured", "true or false", lambda v: isinstance(v, bool)),
)

MAX_FILE_BYTES = 64 << 20  # a DAVIS346's file is ~0.5 MB, most of it the noise rates


def load(path: Path | str) -> Calibration:
    """Read and check a calibration file; any defect is one ConfigError naming the file."""
    try:
        data = json.loads(read_limited(path, MAX_FILE_BYTES).decode("utf-8-sig"))  # -sig: a BOM (hand edits)
    except OSError as exc:
        raise ConfigError(f"cannot read calibration {path} ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ConfigError(f"calibration {path} is not a JSON file ({exc})") from None
    except RecursionError:
        raise ConfigError(f"calibration {path} is not a calibration (arrays or objects nested too deep)") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or data.get("version") != VERSION:
        raise ConfigError(f"calibration {path} is not an {FORMAT} file of version {VERSION}")
    try:
        values = {f.name: data[f.name] for f in dataclasses.fields(Calibration) if f.name in data and f.name != "noise"}
        cal = Calibration(**values)
    except TypeError as exc:
        raise ConfigError(f"calibration {path} lacks a field ({exc})") from None
    bad = [f"{name}={getattr(cal, name)!r} ({rule})" for name, rule, ok in _FIELD_RULES if not ok(getattr(cal, name))]
    if bad:
        raise ConfigError(f"calibration {path} holds values out of range: {'; '.join(bad)}")
    if data.get("noise") is not None:
        cal = dataclasses.replace(cal, noise=_decode_noise(data["noise"], (cal.height, cal.width), path))
    return cal


_NOISE_ARRAYS = ("on_hz", "off_hz", "seconds")  # NoiseRates fields, saved under the same keys
_NOISE_ENCODING = "zlib+base64 float16 little-endian, row-major (height, width)"


def _encode_noise(noise: NoiseRates) -> dict[str, Any]:
    out: dict[str, Any] = {"encoding": _NOISE_ENCODING, "shape": list(noise.shape)}
    for key in _NOISE_ARRAYS:
        raw = np.ascontiguousarray(np.clip(getattr(noise, key), 0, 65000), "<f2").tobytes()
        out[key] = base64.b64encode(zlib.compress(raw, 6)).decode("ascii")
    return out


def _decode_noise(data: Any, shape: tuple[int, int], path: Path | str) -> NoiseRates:
    """The per-pixel noise rates of a calibration file; any defect is one ConfigError naming the file."""
    if not isinstance(data, dict) or data.get("encoding") != _NOISE_ENCODING or data.get("shape") != list(shape):
        raise ConfigError(f"calibration {path}: its per-pixel noise rates are not {_NOISE_ENCODING} arrays of "
                          f"{shape[1]}x{shape[0]}")
    arrays = []
    want = 2 * shape[0] * shape[1]  # float16 bytes
    for key in _NOISE_ARRAYS:
        try:
            # at most one byte past the size expected: a few MB of zeros compressed 1000:1 (a "zip bomb", by
            # hand or by accident) was inflated whole, 8.7 GB of memory for a 5.5 MB file
            inflate = zlib.decompressobj()
            raw = inflate.decompress(base64.b64decode(str(data[key]), validate=True), want + 1)
        except (KeyError, binascii.Error, zlib.error, ValueError) as exc:
            raise ConfigError(f"calibration {path}: per-pixel noise rates {key!r} cannot be read ({exc})") from None
        a = np.frombuffer(raw, "<f2") if len(raw) == want else None  # (an odd length is no float16 array)
        if a is None or not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ConfigError(f"calibration {path}: per-pixel noise rates {key!r} are not {shape[1]}x{shape[0]} "
                              f"finite non-negative values")
        arrays.append(a.astype(np.float32).reshape(shape))
    return NoiseRates(*arrays)


def check_can_save(path: Path | str) -> None:
    """ConfigError now, rather than after the run has measured everything, when save() could not write `path`:
    a missing folder that cannot be made, a read-only place, or a target that is not a regular file (the rename
    would replace a device or a pipe). Leaves nothing behind but the folder save() would make anyway."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        _check_regular(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.open("w").close()
        tmp.unlink()
    except (FileExistsError, NotADirectoryError):  # a file where a folder of the path should be ("File exists")
        blocker = next((p for p in reversed(path.parents) if p.exists() and not p.is_dir()), path.parent)
        raise ConfigError(f"cannot write calibration {path} ({blocker} is a file, not a folder)") from None
    except OSError as exc:
        raise ConfigError(f"cannot write calibration {path} ({exc.strerror or exc})") from None


def _check_regular(path: Path) -> None:
    if path.exists() and not path.is_file():
        raise ConfigError(f"cannot write calibration {path} (it exists and is not a regular file)")


def save(cal: Calibration, path: Path | str) -> None:
    """Write atomically (a temporary file renamed over the target), creating the folder. A symbolic link is
    written through: its target is replaced, the link stays (a calibration kept with a user's dotfiles)."""
    path = Path(path)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    _check_regular(path)
    data: dict[str, Any] = {"format": FORMAT, "version": VERSION,
                            **{f.name: getattr(cal, f.name) for f in dataclasses.fields(cal) if f.name != "noise"}}
    if cal.noise is not None:
        data["noise"] = _encode_noise(cal.noise)
    data["saved"] = data["saved"] or time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    tmp = path.with_name(path.name + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(json.dumps(data, indent=1) + "\n")
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):  # no half-written file left next to the target
            tmp.unlink(missing_ok=True)
        # a runtime failure (a full disk), not a usage error: where to write was checked before the run
        raise OutputError(f"cannot write calibration {path} ({exc.strerror or exc})") from None


def prepare(edi: EdiConfig, info: SourceInfo, given: Path | None, save_to: Path | None) -> tuple[EdiConfig, Path | None]:
    """The EDI settings to start with (a loaded calibration as the estimates' starting values), and where to
    save the calibration at the end. A live camera without --calibration loads its own file if there is one, and
    saves to it."""
    live = info.kind in ("usb", "emulator")
    own = live and missing_home() is None and default_path(info).is_file()
    path = given if given is not None else (default_path(info) if own else None)
    if path is not None:
        try:
            cal = load(path)
        except ConfigError as exc:
            if given is not None:
                raise
            # the camera's own file, damaged (a hand edit): no flag named it, so it must not stop the camera; it is
            # kept as it is, for the user to mend, rather than saved over
            log.warning("%s; not using it, nor saving this run's calibration over it (mend or delete the file)", exc)
            return edi, save_to
        try:
            cal.check_for(info, path)
        except ConfigError as exc:
            if given is not None:
                raise
            log.warning("%s; not using it", exc)  # the camera's own file, but of another sensor set-up
            return edi, save_to if save_to is not None else _own_target(info)
        log.info("starting from the calibration %s (c_on=%.3f c_off=%.3f, black level %g DN%s, clock offset %d µs%s)",
                 path, cal.c_on, cal.c_off, cal.black_level,
                 " measured on dark frames" if cal.black_level_measured else "", cal.clock_offset_us,
                 ", per-pixel noise rates" if cal.noise is not None else "")
        edi = dataclasses.replace(edi, start=cal, aps_gamma=cal.aps_gamma if edi.aps_gamma is None else edi.aps_gamma)
        if cal.black_level_measured and edi.black_level is None:  # measured on dark frames: not a starting value
            edi = dataclasses.replace(edi, black_level=cal.black_level)
    return edi, save_to if save_to is not None else (_own_target(info) if live else None)


def from_stats(info: SourceInfo, stats: dict, noise: NoiseRates | None = None,
               start: Calibration | None = None, black_level_flag: bool = False) -> Calibration | None:
    """The calibration a finished run used last (its stats, and the per-pixel noise rates it estimated, if any),
    or None when it never had thresholds. `start`: the calibration the run started from, whose measured black
    level stays measured while the run used it, and also when a flag or TOML key (`black_level_flag`) replaced it
    for this run only: a measurement is not lost to one run's override."""
    c_on, c_off = stats.get("c_on"), stats.get("c_off")
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (c_on, c_off)):
        return None
    if noise is not None and noise.shape != (info.height, info.width):
        noise = None
    black = float(stats.get("black_level_dn") or 0.0)
    # the stats round the black level to 0.01 DN: within that, the run used the measured value as given
    measured = start is not None and start.black_level_measured and (black_level_flag
                                                                    or abs(black - start.black_level) < 0.006)
    if measured:
        black = start.black_level
    return Calibration(info.label, info.width, info.height, float(c_on), float(c_off), black,
                       int(stats.get("clock_offset_us") or 0), float(stats.get("aps_gamma") or 1.0), noise=noise,
                       black_level_measured=measured)


def measured(info: SourceInfo, stats: dict, noise: NoiseRates | None, start: Calibration | None,
             black_level_flag: bool, target: Path | str) -> Calibration | None:
    """from_stats for saving to `target`: an OutputError when the run measured nothing (fewer than two APS frames
    deblurred: no frame pair, so the values are the defaults or the start's, whose noise rates would be lost),
    so that a file that is there stays as it was."""
    deblurred = int(stats.get("frames_deblurred") or 0)
    if deblurred < 2:
        raise OutputError(f"nothing to save in {target}: {deblurred} APS frame(s) deblurred, and the calibration is "
                          f"measured on pairs of them; the file is left as it was")
    return from_stats(info, stats, noise, start, black_level_flag)
