"""The program's standard output and error when they are not a UTF-8 terminal: a service's journal, a pipe, a
C locale with PYTHONIOENCODING=ascii.

Owns three things: file descriptors 0-2 that were closed are filled with /dev/null (so that no file of ours
takes their number); text a stream cannot encode ("µs" on an ASCII stream) is written escaped (`\\xb5s`) instead of
raising UnicodeEncodeError, which turned `--help` into an internal error; and a reader of stdout that went away
(`edi-live --list-devices | head -0`) ends the output quietly instead of a BrokenPipeError (a stdout that
cannot take the lines, such as a full disk, is an OutputError).
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable
from typing import Any

from edi_live.errors import OutputError


def occupy_closed_standard_fds() -> None:
    """Open /dev/null on file descriptors 0-2 where they were closed (`2>&-`, a bare service environment).

    Otherwise the next file opened takes the number: with `2>&-` the --out recording became fd 2, and whatever a
    library writes to "stderr" at C level (libzmq, libusb, OpenCV messages) went into the middle of it."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            try:
                null = os.open(os.devnull, os.O_RDWR)
            except OSError:
                return
            if null != fd:  # (a lower one was free too: it is filled on its own turn of the loop)
                os.dup2(null, fd)
                os.close(null)


def escape_what_cannot_be_encoded() -> None:
    """stdout/stderr whose encoding cannot hold our messages' non-ASCII text escape it from now on.

    Only the error handler changes (not the encoding), and only on such streams: a UTF-8 one is left alone."""
    for stream in (sys.stdout, sys.stderr):
        if not _can_encode(stream, "µ–×"):
            try:
                stream.reconfigure(errors="backslashreplace")
            except (AttributeError, ValueError, OSError):  # not a TextIOWrapper, or closed: nothing to do
                pass


def _can_encode(stream: Any, text: str) -> bool:
    encoding = getattr(stream, "encoding", None)
    if stream is None or not encoding:
        return True
    try:
        text.encode(encoding, getattr(stream, "errors", None) or "strict")
    except (UnicodeError, LookupError):
        return False
    return True


def print_lines(lines: Iterable[str]) -> None:
    """The lines on stdout; a reader that closed the pipe early ends them without an error (it has what it
    wanted), and stdout goes to /dev/null so that the interpreter's last flush is quiet too. Any other failure to
    write them raises OutputError."""
    if sys.stdout is None:  # started with stdout closed (`>&-`): there is no one to tell
        return
    try:
        for line in lines:
            print(line)
        sys.stdout.flush()
    except BrokenPipeError:
        _stdout_to_devnull()
    except OSError as exc:  # a full disk, an I/O error: the lines are lost, which the user must hear
        _stdout_to_devnull()
        raise OutputError(f"cannot write to stdout ({exc.strerror or exc})") from None


def _stdout_to_devnull() -> None:
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, sys.stdout.fileno())
        os.close(null)
    except (OSError, ValueError, AttributeError):  # no file descriptor behind stdout: nothing to silence
        pass
