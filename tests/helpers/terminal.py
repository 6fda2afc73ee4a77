"""A small model of a terminal's screen, for what a live status line leaves on it when the window is resized.

A pty only carries bytes; what stays on the screen after a resize is the terminal's doing. Modelled here: printable
characters with autowrap at the right margin, CR, LF (as CR LF: a pty's onlcr), erase to end of line (ESC [ K)
and to end of screen (ESC [ J), cursor up (ESC [ n A), and a resize either re-wrapping soft-wrapped rows into the new width (tmux,
GNOME Terminal, kitty, iTerm2: a row that wrapped joins its continuation and the cursor keeps its place in that
text) or cutting rows at the new width (xterm, the Linux console). Nothing else (no other cursor movement, no
scrolling region); an unknown escape sequence is an error, so a new one cannot pass unseen.
"""

from __future__ import annotations

import re

_CSI = re.compile(r"\x1b\[([0-9;]*)([A-Za-z])")


class Screen:
    def __init__(self, columns: int, reflow: bool = True) -> None:
        self.columns, self.reflow = columns, reflow
        self.rows: list[list[str]] = [[]]
        self.wrapped = [False]  # row i continues on row i + 1 (it filled the width)
        self.x = self.y = 0

    def write(self, text: str) -> None:
        i = 0
        while i < len(text):
            m = _CSI.match(text, i)
            if m:
                self._csi(m.group(1), m.group(2))
                i = m.end()
                continue
            ch = text[i]
            i += 1
            if ch == "\r":
                self.x = 0
            elif ch == "\n":
                self._down()
            elif ch == "\x1b":
                raise ValueError(f"escape sequence not modelled: {text[i - 1:i + 8]!r}")
            else:
                if self.x >= self.columns:  # the pending wrap of a full row
                    self.wrapped[self.y] = True
                    self._down()
                row = self.rows[self.y]
                row.extend(" " * (self.x - len(row)))
                if self.x < len(row):
                    row[self.x] = ch
                else:
                    row.append(ch)
                self.x += 1

    def _down(self) -> None:
        self.y, self.x = self.y + 1, 0
        if self.y == len(self.rows):
            self.rows.append([])
            self.wrapped.append(False)

    def _csi(self, arg: str, op: str) -> None:
        if op == "K" and arg in ("", "0"):
            del self.rows[self.y][self.x:]
            self.wrapped[self.y] = False
        elif op == "A":  # cursor up, stopping at the top row
            self.y = max(0, self.y - int(arg or "1"))
        elif op == "J" and arg in ("", "0"):
            del self.rows[self.y][self.x:]
            del self.rows[self.y + 1:]
            del self.wrapped[self.y + 1:]
            self.wrapped[self.y] = False
        else:
            raise ValueError(f"escape sequence not modelled: ESC[{arg}{op}")

    def resize(self, columns: int) -> None:
        if not self.reflow:
            self.rows = [row[:columns] for row in self.rows]
            self.wrapped = [False] * len(self.rows)
            self.columns, self.x = columns, min(self.x, columns)
            return
        lines: list[list[str]] = []
        cursor = (0, 0)
        current: list[str] = []
        for i, row in enumerate(self.rows):
            if i == self.y:
                cursor = (len(lines), len(current) + self.x)
            current += row + [" "] * (self.columns - len(row)) if self.wrapped[i] else row
            if not self.wrapped[i]:
                lines.append(current)
                current = []
        if current:
            lines.append(current)
        self.columns = columns
        self.rows, self.wrapped = [], []
        for n, line in enumerate(lines):
            start = len(self.rows)
            chunks = [line[k:k + columns] for k in range(0, len(line), columns)] or [[]]
            self.rows += chunks
            self.wrapped += [True] * (len(chunks) - 1) + [False]
            if n == cursor[0]:
                offset = cursor[1]
                self.y, self.x = start + offset // columns, offset % columns
                if offset and offset % columns == 0 and offset >= len(line):  # just after a full row: stays there
                    self.y, self.x = self.y - 1, columns
                while self.y >= len(self.rows):
                    self.rows.append([])
                    self.wrapped.append(False)

    def text(self) -> list[str]:
        """The screen's rows, trailing blanks cut, without the empty rows at the bottom."""
        out = ["".join(row).rstrip() for row in self.rows]
        while out and not out[-1]:
            out.pop()
        return out
