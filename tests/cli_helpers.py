"""Helpers of the command-line tests: run ``python -m pyrtu`` as a subprocess, with
bounded timeouts, from the root of the tree under test."""

from __future__ import annotations

import json
import os
import queue
import random
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 30.0


def poll_weg(timeout: float, bus: str = "") -> str:
    """A ``pyrtu poll --config`` file: the bus "line1" on ``{port}`` (to be formatted)
    at 115200 8N1, this timeout, a short back-off (``bus``: more lines of its table);
    a CFW701 "weg" at 1 every 50 ms."""
    return f"""\
[[bus]]
name = "line1"
port = "{{port}}"
baudrate = 115200
parity = "N"
timeout = {timeout}
{bus}backoff = 0.1
max_backoff = 0.4

[[device]]
bus = "line1"
slave = 1
profile = "cfw701"
name = "weg"
interval = 0.05
"""


#: The start of a ``pyrtu poll --config`` file: the bus "line1" on ``{port}`` (to be
#: formatted) at 115200 8N1 with short timeouts, the default for every point after it.
POLL_BUS = """\
[defaults]
bus = "line1"
interval = 0.05

[[bus]]
name = "line1"
port = "{port}"
baudrate = 115200
parity = "N"
timeout = 0.05
offline_after = 2
"""


@dataclass
class Result:
    code: int
    out: str
    err: str

    def json(self) -> Any:
        """The one JSON document on stdout."""
        lines = self.json_lines()
        assert len(lines) == 1, self.out
        return lines[0]

    def json_lines(self) -> list[Any]:
        return [json.loads(line) for line in self.out.splitlines() if line.strip()]


def env() -> dict[str, str]:
    e = dict(os.environ)
    e.pop("PYTHONSTARTUP", None)
    e["PYTHONUNBUFFERED"] = "1"
    e.setdefault("TERM", "dumb")
    return e


def pyrtu(*args: object, timeout: float = TIMEOUT) -> Result:
    """Run ``python -m pyrtu ARGS`` to completion."""
    proc = subprocess.run(
        [sys.executable, "-m", "pyrtu", *map(str, args)],
        cwd=ROOT,
        env=env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    return Result(proc.returncode, proc.stdout, proc.stderr)


def kill_after_each_test(started: list[subprocess.Popen[str]]) -> Any:
    """An autouse fixture for a test module whose tests start processes into
    ``started``: after every test, each one still running is killed and reaped, so
    that a test that fails while one runs does not leave it running."""

    @pytest.fixture(autouse=True)
    def kill_left() -> Iterator[None]:
        yield
        while started:
            p = started.pop()
            if p.poll() is None:
                p.kill()
                p.communicate(timeout=10)

    return kill_left


class Background:
    """``python -m pyrtu ARGS`` running; its stdout lines arrive in a queue."""

    def __init__(self, *args: object) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", *map(str, args)],
            cwd=ROOT,
            env=env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.err: list[str] = []
        self.out: list[str] = []
        self._threads = [
            threading.Thread(target=self._read_out, daemon=True),
            threading.Thread(target=self._read_err, daemon=True),
        ]
        for t in self._threads:
            t.start()

    def _read_out(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line)

    def _read_err(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            self.err.append(line)

    def line(self, timeout: float = 10.0) -> str:
        """The next line of stdout (queue.Empty after ``timeout``)."""
        line = self.lines.get(timeout=timeout)
        self.out.append(line)
        return line

    def finish(self, timeout: float = 15.0) -> Result:
        """Wait for the end (killed after ``timeout``); everything it printed."""
        try:
            self.proc.wait(timeout)
        finally:
            self.kill()
        for t in self._threads:
            t.join(5)
        while not self.lines.empty():
            self.out.append(self.lines.get_nowait())
        return Result(self.proc.returncode, "".join(self.out), "".join(self.err))

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


def free_port_range(count: int) -> int:
    """The first of ``count`` consecutive loopback ports free now, below the ephemeral
    ports (so that no connection of anyone's takes one of them meanwhile)."""
    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    for _ in range(200):
        first = random.randrange(10000, low - count)
        held: list[socket.socket] = []
        try:
            for port in range(first, first + count):
                held.append(socket.socket())
                held[-1].bind(("127.0.0.1", port))
        except OSError:
            continue
        finally:
            for s in held:
                s.close()
        return first
    raise AssertionError(f"no {count} consecutive free ports")
