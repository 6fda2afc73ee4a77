"""The TOML config file: reading it into the flat option mapping (one key per flag, paths relative to the file),
merging the command line's flags over it, and the converters of the option table's values. Every problem is one
ConfigError naming the file."""

from __future__ import annotations

import errno
import os
import select
import stat
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from edi_live.checks import check as _check
from edi_live.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 only
    import tomli as tomllib


def norm_key(key: str) -> str:
    """An option's key as the config uses it: `--stats-interval-s` and `stats-interval-s` are `stats_interval_s`."""
    return key.strip().lstrip("-").replace("-", "_")


MAX_CONFIG_BYTES = 1 << 20
ONE_SHOT_ACTIONS = ("list_devices", "calibrate_dark", "version")
"""Flags that do something once and exit instead of configuring a run: never in a config file."""


PIPE_WAIT_S = 5.0
"""How long a pipe or FIFO given as a file may take to deliver all of it (bash's <(...) delivers at once)."""


def read_limited(path: str | Path, limit: int) -> bytes:
    """The file's bytes; ValueError past `limit` bytes, read no further: a recording or a device given by mistake
    (--config /dev/zero, --calibration rec.aedat4) would otherwise be read into memory whole, or for ever.
    A pipe or FIFO must be written and closed within PIPE_WAIT_S, else OSError(ETIMEDOUT)."""
    # O_NONBLOCK: a FIFO that no program writes to blocked open() for ever, and Ctrl-C only sets the stop flag
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        if stat.S_ISFIFO(os.fstat(fd).st_mode):
            data = _read_pipe(fd, limit, path)
        else:
            os.set_blocking(fd, True)
            with os.fdopen(fd, "rb", closefd=False) as fh:
                data = fh.read(limit + 1)
    finally:
        os.close(fd)
    if len(data) > limit:
        raise ValueError(f"larger than {limit >> 20} MiB, far more than such a file holds")
    return data


def _read_pipe(fd: int, limit: int, path: str | Path) -> bytes:
    """Up to limit + 1 bytes of a pipe, until its writer closes it, waiting at most PIPE_WAIT_S in all. Before any
    writer opened a FIFO, poll() reports nothing (not even a hang-up), so the wait covers a writer started later."""
    deadline = time.monotonic() + PIPE_WAIT_S
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    data = bytearray()
    while len(data) <= limit:
        left_ms = (deadline - time.monotonic()) * 1000
        if left_ms <= 0 or not poller.poll(left_ms):
            raise OSError(errno.ETIMEDOUT, f"it is a pipe that nothing wrote to and closed within {PIPE_WAIT_S:g} s: "
                                           f"start its writer first, or give a regular file", str(path))
        try:
            chunk = os.read(fd, limit + 1 - len(data))
        except BlockingIOError:  # woken without data (a writer came and went, another is still there)
            continue
        if not chunk:
            break
        data += chunk
    return bytes(data)


def read_toml(path: str | Path, known: Iterable[str]) -> dict[str, Any]:
    """The flat key -> value mapping of a TOML config file, whose keys must be among `known`; ConfigError naming
    the file on any problem."""
    path = Path(path)
    try:
        data = tomllib.loads(read_limited(path, MAX_CONFIG_BYTES).decode("utf-8-sig"))  # -sig: a BOM (Notepad)
    except FileNotFoundError:
        raise ConfigError(f"config file {path} not found") from None
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # a binary file: TOML is UTF-8 text
        raise ConfigError(f"config file {path} is not a TOML text file (not UTF-8 at byte {exc.start}); give "
                          f"--config a .toml file") from None
    except (ValueError, RecursionError) as exc:  # anything else the parser trips over is still the file's fault
        raise ConfigError(f"config file {path} is not valid TOML ({type(exc).__name__}: {exc})") from None
    nested = [k for k, v in data.items() if isinstance(v, dict)]
    _check(not nested, f"config file {path}: keys go at the top level, like the flags (got table(s) {nested})")
    spellings: dict[str, list[str]] = {}
    for key in data:  # `c-on` and `c_on` are two keys to TOML, one option to us: one of the values would be lost
        spellings.setdefault(norm_key(key), []).append(key)
    twice = "; ".join(" and ".join(repr(k) for k in keys) for keys in spellings.values() if len(keys) > 1)
    _check(not twice, f"config file {path}: one option given twice ({twice}); keep one of them")
    normalized = {norm_key(k): v for k, v in data.items()}
    known = set(known)
    for key in data:
        _check(norm_key(key) not in ONE_SHOT_ACTIONS, f"config file {path}: {key} is a one-shot action, not a "
               f"setting: give it as a flag (--{norm_key(key).replace('_', '-')})")
    unknown = sorted(k for k in data if norm_key(k) not in known)  # as written: `c-onn`, not `c_onn`
    _check(not unknown, f"config file {path}: unknown key(s) {', '.join(unknown)}")
    base = path.parent
    for key in ("replay", "out", "record", "emulate_from", "curve_secret_key", "calibration", "save_calibration"):
        # relative paths in a config file are relative to the file, not to the working directory; ~ is the home
        # folder, as a shell would read it in a flag
        if isinstance(normalized.get(key), str) and normalized[key]:  # ("" stays "": as_path refuses it)
            given = Path(os.path.expanduser(normalized[key]))  # (Path.expanduser raises on an unknown ~user)
            normalized[key] = str(given if given.is_absolute() else base / given)
    return normalized


def merge_options(file_options: Mapping[str, Any], flag_options: Mapping[str, Any]) -> dict[str, Any]:
    """Flags override the file. A device flag replaces a replay from the file and vice versa."""
    merged = {norm_key(k): v for k, v in file_options.items()}
    flags = {norm_key(k): v for k, v in flag_options.items()}
    for given in ("device", "replay", "dv_input"):  # an input flag replaces the file's input
        if given in flags:
            for other in {"device", "replay", "dv_input"} - {given}:
                merged.pop(other, None)
    if "publish" in flags:
        merged.pop("no_publish", None)
    if flags.get("no_publish"):
        merged.pop("publish", None)
    merged.update(flags)
    return merged


# converters of the option table (edi_live.config.OPTION_KEYS): a TOML value or a flag's into the field's type
def as_path(v: Any) -> Path | None:
    if v is not None and not isinstance(v, (str, os.PathLike)):  # Path(3)'s own message is Python's, not ours
        raise TypeError("expected a file path")
    if v is not None and not os.fspath(v):  # Path("") is ".": an unset shell variable would name the folder
        raise ValueError("expected a file path, not an empty one")
    if v is not None and "\0" in os.fsdecode(v):  # TOML's "\u0000": open() would fail with "embedded null byte"
        raise ValueError("a file path cannot hold a NUL character")
    return None if v is None else Path(v)


def as_endpoints(v: Any) -> tuple[str, ...]:
    if isinstance(v, str):
        return (v,)
    if not isinstance(v, (list, tuple)):  # publish and dv-input: the caller names the key
        raise TypeError("expected a list of endpoints")
    return tuple(v)


def as_number(v: Any) -> Any:
    _check(not isinstance(v, bool), f"expected a number, not {str(v).lower()} (got {v!r})")
    return float(v) if isinstance(v, int) else v


def as_bool(name: str) -> Callable[[Any], bool]:
    """A switch must be true or false: `loop = "false"` in a TOML file is a string, which Python finds true."""

    def convert(v: Any) -> bool:
        _check(isinstance(v, bool), f"{name} must be true or false (got {v!r})")
        return v

    return convert
