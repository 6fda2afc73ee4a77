"""The files one run reads and the files it writes, and the check that keeps them apart: no file the run writes
(--out, --record, --save-calibration) may be a file it reads (--replay, --emulate-from, --calibration, --config)
or another file it writes, however the two paths are spelled (relative, absolute, through a link). Pure path logic:
it stats paths but opens nothing.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

from edi_live.checks import check


def same_file(a: Path | str, b: Path | str) -> bool:
    """Whether two paths name one file (also through links, or relative vs absolute spellings)."""
    try:
        if Path(a).exists() and Path(b).exists():
            return os.path.samefile(a, b)
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):  # RuntimeError: a symlink loop (Python < 3.13), which names no file
        return False


def check_apart(reads: Mapping[str, Path | None], writes: Mapping[str, Path | None],
                may_update: Mapping[str, str] | None = None) -> None:
    """ConfigError unless every written file differs from every read file and from every other written file.
    Keys are the flags' names; `may_update` maps a written flag to the read flag it may rewrite (a calibration
    saved over the one it started from)."""
    may_update = may_update or {}
    written = [(flag, path) for flag, path in writes.items() if path is not None]
    for flag, path in written:
        for source_flag, read in reads.items():
            if read is None or may_update.get(flag) == source_flag:
                continue
            what = "recording" if source_flag in ("replay", "emulate-from") else "file"
            check(not same_file(path, read), f"{flag} would overwrite the {source_flag} {what} it reads (got "
                                             f"{str(path)!r}); choose another file name")
    for i, (flag, path) in enumerate(written):
        for other, other_path in written[i + 1:]:
            check(not same_file(path, other_path),
                  f"{flag} and {other} must be different files (got {str(path)!r} twice)")
