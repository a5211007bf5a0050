"""Test helper: a ``pyrtu`` command on a pseudo-terminal of a given size, its output
fed to a terminal emulator (pyte, an independent VT100/xterm implementation) as it
comes, so that a test sees what a user's screen shows: the screen, the lines that
scrolled off its top, and whether a line ever reached the last column (where a
terminal wraps it onto the next row).

Both stdout and stderr are the terminal, as in a user's shell.
"""

from __future__ import annotations

import fcntl
import os
import pty
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import pyte
from cli_helpers import ROOT, env


def screen_line(line: dict[int, pyte.screens.Char], columns: int) -> str:
    return "".join(line[x].data for x in range(columns)).rstrip()


@dataclass
class Terminal:
    """A command running on a ``columns`` x ``rows`` pseudo-terminal."""

    columns: int
    rows: int
    raw: bytearray = field(default_factory=bytearray)
    #: the rows that ever had a character in their last column: (the offset in
    #: `raw` of the byte that put it there, the row's text)
    touched_last_column: list[tuple[int, str]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.screen = pyte.HistoryScreen(self.columns, self.rows, history=100_000)
        self.stream = pyte.ByteStream(self.screen)
        self.proc: subprocess.Popen[bytes] | None = None
        self.master = -1

    def start(self, *args: object, extra_env: dict[str, str] | None = None) -> None:
        self.master, slave = pty.openpty()
        self.resize(self.columns, self.rows, slave)
        e = {**env(), "TERM": "xterm", **(extra_env or {})}
        e.pop("COLUMNS", None)  # the size is the terminal's, not the environment's
        e.pop("LINES", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", *map(str, args)],
            cwd=ROOT,
            env=e,
            stdin=slave,
            stdout=slave,
            stderr=slave,
            start_new_session=True,  # the pty becomes its controlling terminal
        )
        os.close(slave)

    def resize(self, columns: int, rows: int, fd: int | None = None) -> None:
        """Give the terminal a new size (the kernel sends SIGWINCH to the command)."""
        fcntl.ioctl(self.master if fd is None else fd, termios.TIOCSWINSZ,
                    struct.pack("HHHH", rows, columns, 0, 0))  # fmt: skip
        self.columns, self.rows = columns, rows
        self.screen.resize(rows, columns)
        if fd is None and self.proc is not None:
            self.proc.send_signal(signal.SIGWINCH)  # not our session's terminal: by hand

    def pump(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        """Feed the emulator what comes for up to ``seconds``; True when the command
        closed the terminal (it ended) or ``until()`` became true."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if until is not None and until():
                return True
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            try:
                chunk = os.read(self.master, 65536)
            except OSError:  # EIO: the command closed the terminal
                return True
            if not chunk:
                return True
            self.feed(chunk)
        return False

    def feed(self, chunk: bytes) -> None:
        start = len(self.raw)
        self.raw += chunk
        for offset, byte in enumerate(chunk, start):  # every intermediate state
            self.stream.feed(bytes([byte]))
            if self.screen.cursor.x >= self.columns:  # a character went to the last
                # column: the next one goes to the next row (a wrap)
                text = screen_line(self.screen.buffer[self.screen.cursor.y], self.columns)
                if not self.touched_last_column or self.touched_last_column[-1][1] != text:
                    self.touched_last_column.append((offset, text))

    def finish(self, timeout: float = 60.0) -> int:
        """Read until the command ends; its exit status."""
        assert self.proc is not None
        try:
            self.pump(timeout)
            return self.proc.wait(timeout=15)
        finally:
            self.close()

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        if self.master >= 0:
            os.close(self.master)
            self.master = -1

    def wrapped(self, start: bytes, end: bytes) -> list[str]:
        """The rows that reached the last column while what was written from the first
        ``start`` to the last ``end`` (or to the end) came: a live view's time."""
        first = self.raw.find(start)
        assert first >= 0, f"{start!r} never came"
        last = self.raw.rfind(end)
        last = len(self.raw) if last < first else last
        return [text for offset, text in self.touched_last_column if first <= offset < last]

    def display(self) -> list[str]:
        """The screen's rows now, without trailing blanks."""
        return [line.rstrip() for line in self.screen.display]

    def scrollback(self) -> list[str]:
        """The rows that scrolled off the top, oldest first."""
        return [screen_line(line, self.columns) for line in self.screen.history.top]

    def everything(self) -> list[str]:
        """The scrollback and then the screen: all a user can still see."""
        return self.scrollback() + self.display()
