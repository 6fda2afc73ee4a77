"""One line of text redrawn in place on a terminal (the node's status line, the viewer's): the escape text to
draw it and to end it, and the logging handler that erases it before a message; stdlib only.

A line wider than the terminal is laid out in up to MAX_ROWS rows, whole fields per row (fields beyond them are
dropped): a line left to wrap by itself leaves a row behind at every redraw, since '\\r' returns to its last row
only, and cutting it to one row hid the camera values at its end on an 80-column terminal. The width can change
while it runs, and terminals that re-wrap their text on a resize (tmux, GNOME Terminal, kitty, iTerm2) turn each
drawn row into several at a shrink. So between draws the cursor is parked at the start of the block's first row,
where every terminal keeps it, and a redraw erases to the end of the screen: whatever rows the old block became,
none is left behind, whether the terminal re-wraps or cuts its rows (xterm, the Linux console).
"""

from __future__ import annotations

import io
import logging
import os
from typing import Any

ERASE = "\r\x1b[J"
"""Erases the live line (and any rows a resize made of it): written before a message that takes its place."""


def columns(stream: Any) -> int:
    """The width of the terminal behind `stream` now; COLUMNS, else 80, when unknown. A terminal whose size was
    never set (a pty made by `script`, some CI runners and containers) says 0 columns: unknown too."""
    try:
        width = os.get_terminal_size(stream.fileno()).columns
        if width > 0:
            return width
    except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
        pass
    try:
        return max(1, int(os.environ.get("COLUMNS", "")))
    except ValueError:
        return 80


MAX_ROWS = 3


def rows(line: str, width: int, sep: str = "  ") -> list[str]:
    """`line` in rows of at most `width` characters, whole fields (separated by `sep`) per row, at most MAX_ROWS
    rows: the fields that do not fit in them are dropped; a field longer than a row is cut."""
    if len(line) <= width:
        return [line]
    out: list[str] = []
    row = None
    for field in line.split(sep):
        if row is not None and len(row) + len(sep) + len(field) <= width:
            row += sep + field
            continue
        if row is not None:
            out.append(row)
            if len(out) == MAX_ROWS:
                return out
        row = field[:max(1, width)]
    out.append(row or "")
    return out


def _block(line: str, width: int, sep: str) -> tuple[str, int]:
    """The rows of `line` written over the old block from its start (one column is kept free: a row filled to the
    margin wraps in some terminals), the rest of each row and of the screen erased; and how many rows."""
    laid = rows(line, width - 1, sep)
    return "\r" + "\x1b[K\n".join(laid) + "\x1b[J", len(laid)


def redraw(line: str, width: int, sep: str = "  ") -> str:
    """The text that replaces the live block by `line` on a terminal `width` columns wide, the cursor parked at
    the start of its first row."""
    text, n = _block(line, width, sep)
    return text + (f"\x1b[{n - 1}A" if n > 1 else "") + "\r"


def end(line: str | None, width: int, sep: str = "  ") -> str:
    """The text that leaves `line` (the last one drawn) on the screen and puts the cursor on the row below it. It
    is drawn once more: a log message may have taken its place, and the terminal may have re-wrapped it since."""
    if line is None:
        return ""
    return _block(line, width, sep)[0] + "\n"


class LogHandler(logging.StreamHandler):
    """Logging that first erases the live line on a terminal (it is redrawn at the next tick); without this a
    message was glued to the end of the line, and with the cursor parked at the line's start it would overwrite
    the line's first characters only."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        isatty = getattr(self.stream, "isatty", None)
        return ERASE + text if isatty is not None and isatty() else text
