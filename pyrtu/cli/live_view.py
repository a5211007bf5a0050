"""A live view: a block of lines redrawn in place at the bottom of a terminal.

One `LiveView` owns its terminal while it is shown: the frames it draws and any
line printed meanwhile (an event, a message) go through it, never around it, so
that the cursor movements of a redraw always land on the view's own lines.

Every frame fits the terminal it is drawn on, read again at each draw (the size of
the terminal itself, not ``$COLUMNS``): each line is cut to the width less one
column (a line that wraps would take two rows, and the next redraw, counting one
row per line, would leave its remains behind), and the frame to the height less
one row (the cursor rests on the row below it); a frame too tall for the screen
ends with a line that says how many lines are not shown.  When the size changes
between two draws, the screen is cleared and the frame drawn whole: a terminal
that reflows its text on a resize has moved the old frame's lines where no count
of lines can find them.  Only the lines that changed since the last draw are
rewritten otherwise.

Escape sequences in a line (colours, bold) take no columns; a line cut short
ends with a reset of its attributes.
"""

from __future__ import annotations

import os
import re
import shutil
import threading
import unicodedata
from collections.abc import Callable, Sequence
from typing import IO, Any, Protocol

__all__ = ["LiveView", "Writer", "columns", "fit_line", "same_terminal", "terminal_size"]

#: an escape sequence: CSI (ESC [ parameters final), or ESC and one character
_ESCAPE = re.compile(r"\x1b\[[0-?]*[ -/]*[@-~]|\x1b[@-Z\\-_]")

#: the cursor home and the screen cleared
_CLEAR = "\x1b[H\x1b[J"

Size = Callable[[], os.terminal_size]


class Writer(Protocol):
    """Where a view is written: a text stream (only these two methods are used)."""

    def write(self, text: str, /) -> Any: ...

    def flush(self) -> Any: ...


def terminal_size(out: object) -> Size:
    """The size of the terminal the stream ``out`` is written to, asked of the
    terminal at each call (TIOCGWINSZ); where it cannot tell (not a terminal, or
    a size of 0, unknown), ``$COLUMNS``/``$LINES`` or 80x24."""

    def size() -> os.terminal_size:
        try:
            found = os.get_terminal_size(out.fileno())  # type: ignore[attr-defined]
        except (OSError, ValueError, AttributeError):
            return shutil.get_terminal_size()
        if found.columns > 0 and found.lines > 0:
            return found
        fallback = shutil.get_terminal_size()
        return os.terminal_size((found.columns or fallback.columns, found.lines or fallback.lines))

    return size


def same_terminal(first: IO[str], second: IO[str]) -> bool:
    """Whether two streams are written to one terminal (stdout and stderr, usually):
    then what goes to either must go through the view drawn on the other."""
    try:
        a, b = os.fstat(first.fileno()), os.fstat(second.fileno())
        return first.isatty() and second.isatty() and (a.st_rdev, a.st_ino) == (b.st_rdev, b.st_ino)
    except (OSError, ValueError, AttributeError):
        return False


def _char_columns(char: str) -> int:
    if unicodedata.combining(char) or unicodedata.category(char) in ("Cf", "Mn", "Me"):
        return 0
    return 2 if unicodedata.east_asian_width(char) in ("W", "F") else 1


def columns(line: str) -> int:
    """The columns ``line`` takes on a terminal (escape sequences take none)."""
    return sum(_char_columns(c) for c in _ESCAPE.sub("", line))


def fit_line(line: str, width: int) -> str:
    """``line`` cut to at most ``width`` columns, its escape sequences kept (and the
    attributes reset when a line that has some is cut)."""
    if width <= 0:
        return ""
    out: list[str] = []
    used = 0
    pos = 0
    cut = False
    escapes = False
    while pos < len(line):
        match = _ESCAPE.match(line, pos)
        if match is not None:
            out.append(match.group())
            escapes = True
            pos = match.end()
            continue
        char = line[pos]
        wide = _char_columns(char)
        if used + wide > width:
            cut = True
            break
        out.append(char)
        used += wide
        pos += 1
    if cut and escapes:
        out.append("\x1b[0m")
    return "".join(out)


class LiveView:
    """The view on ``out``, a terminal of ``size()`` (see the module)."""

    def __init__(self, out: Writer, size: Size | None = None) -> None:
        self.out = out
        self.size = size if size is not None else terminal_size(out)
        self.shown: list[str] = []  # the lines on the screen, top to bottom
        self.written = 0  # lines written by the last `draw` (the changed ones)
        self.lines: list[str] = []  # the frame last asked for, before it was fitted
        self._drawn_on: os.terminal_size | None = None
        # one writer at a time: a log line from another thread waits for the redraw
        self._lock = threading.RLock()

    def room(self) -> tuple[int, int]:
        """The lines and columns a frame may take on the terminal as it is now."""
        cols, rows = self.size()
        return max(1, rows - 1), max(1, cols - 1)

    def fit(self, lines: Sequence[str]) -> list[str]:
        """``lines`` as they are drawn: each cut to the width, the frame to the height."""
        height, width = self.room()
        shown = list(lines)
        if len(shown) > height:
            hidden = len(shown) - (height - 1)
            shown = [*shown[: height - 1], f"... {hidden} more lines (a taller terminal shows all)"]
        return [fit_line(line, width) for line in shown]

    def draw(self, lines: Sequence[str] | None = None) -> None:
        """Show ``lines`` (default: the last ones again) in place of the last frame;
        the cursor ends below it."""
        with self._lock:
            self._draw(lines)

    def _draw(self, lines: Sequence[str] | None) -> None:
        if lines is not None:
            self.lines = list(lines)
        size = self.size()
        parts: list[str] = []
        if self.shown and size != self._drawn_on:
            parts.append(_CLEAR)  # resized: the old frame is where it reflowed
            self.shown = []
        frame = self.fit(self.lines)
        if self.shown:
            parts.append(f"\x1b[{len(self.shown)}F")  # to the frame's first line
        written = 0
        for i, line in enumerate(frame):
            if i < len(self.shown) and self.shown[i] == line:
                parts.append("\x1b[1E")  # unchanged: next line
            else:
                parts.append(f"\x1b[2K{line}\n")
                written += 1
        if len(frame) < len(self.shown):
            parts.append("\x1b[J")  # clear what the longer frame left below
        self.out.write("".join(parts))
        self.out.flush()
        self.shown = frame
        self.written = written
        self._drawn_on = size

    def erase(self) -> None:
        """Take the frame off the screen (the cursor where its first line was, or at
        the top of a screen resized since the frame was drawn)."""
        if self.shown:
            moved = self.size() != self._drawn_on
            self.out.write(_CLEAR if moved else f"\x1b[{len(self.shown)}F\x1b[J")
            self.out.flush()
        self.shown = []

    def print_above(self, text: str, stream: Writer | None = None) -> None:
        """Print ``text`` (a line or more) above the frame, then draw the frame whole
        again below it.  ``stream``: where the text goes (another stream written to
        the same terminal, such as stderr; default the view's own)."""
        with self._lock:
            self.erase()
            target = stream if stream is not None else self.out
            target.write(text if text.endswith("\n") else text + "\n")
            target.flush()
            if self.lines:
                self._draw(None)

    def above(self, stream: Writer) -> Writer:
        """A stream whose lines are printed above the frame on their way to ``stream``
        (for a logging handler writing to the same terminal)."""
        return _Above(self, stream)

    def close(self) -> None:
        """The frame stays on the screen as last drawn; the view writes no more
        (what is printed next starts below it)."""
        with self._lock:
            self.shown = []
            self.lines = []


class _Above:
    """`LiveView.above`: whole lines go through the view, a partial one waits."""

    def __init__(self, view: LiveView, stream: Writer) -> None:
        self.view = view
        self.stream = stream
        self._partial = ""

    def write(self, text: str, /) -> int:
        lines, _, self._partial = (self._partial + text).rpartition("\n")
        if lines:
            self.view.print_above(lines + "\n", self.stream)
        return len(text)

    def flush(self) -> None:
        """Whole lines are written at once: nothing is held but a partial line."""
