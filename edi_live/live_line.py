"""One line of text redrawn in place on a terminal (the node's status line, the viewer's): the escape text to
draw it and to end it, and the logging handler that erases it before a message; stdlib only.

The line is cut to the terminal's width, dropping whole fields from its end: a line that wraps leaves a row
behind at every redraw, since '\\r' returns to its last row only. The width can change while it runs, and
terminals that re-wrap their text on a resize (tmux, GNOME Terminal, kitty, iTerm2) turn the drawn line into
several rows at a shrink. So between draws the cursor is parked at the line's start, which every terminal keeps
at the start of the line's first row, and a redraw erases to the end of the screen: whatever rows the old line
became, none is left behind, whether the terminal re-wraps or cuts its rows (xterm, the Linux console).
"""

from __future__ import annotations

import io
import logging
import os
from typing import Any

ERASE = "\r\x1b[J"
"""Erases the live line (and any rows a resize made of it): written before a message that takes its place."""


def columns(stream: Any) -> int:
    """The width of the terminal behind `stream` now; COLUMNS, else 80, when unknown."""
    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        try:
            return max(1, int(os.environ.get("COLUMNS", "")))
        except ValueError:
            return 80


def fit_fields(line: str, width: int, sep: str = "  ") -> str:
    """`line` cut to at most `width` characters at a field boundary (fields are separated by `sep`); a first
    field longer than that is cut where it must be."""
    if len(line) <= width:
        return line
    cut = line.rfind(sep, 0, width + len(sep))  # a field may end exactly at `width`
    return line[:cut] if cut > 0 else line[:max(0, width)]


def redraw(line: str, width: int, sep: str = "  ") -> str:
    """The text that replaces the live line by `line` on a terminal `width` columns wide, the cursor parked at its
    start (one column is kept free: a row filled to the margin wraps in some terminals)."""
    return "\r" + fit_fields(line, width - 1, sep) + "\x1b[J\r"  # (written over the old one, then its rest erased)


def end(line: str | None, width: int, sep: str = "  ") -> str:
    """The text that leaves `line` (the last one drawn) on the screen and puts the cursor on the next row. It is
    drawn once more: a log message may have taken its place, and the terminal may have re-wrapped it since."""
    if line is None:
        return ""
    return "\r" + fit_fields(line, width - 1, sep) + "\x1b[J\n"


class LogHandler(logging.StreamHandler):
    """Logging that first erases the live line on a terminal (it is redrawn at the next tick); without this a
    message was glued to the end of the line, and with the cursor parked at the line's start it would overwrite
    the line's first characters only."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        isatty = getattr(self.stream, "isatty", None)
        return ERASE + text if isatty is not None and isatty() else text
