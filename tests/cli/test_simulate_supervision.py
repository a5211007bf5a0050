"""``pyrtu simulate``'s background parts are supervised: the real command is run with
one of them made to fail (a small wrapper patches a function, then calls
`pyrtu.cli.main`: the fault is the point), and what the user sees is checked: a
TCP server task that raises is reported (a line, a ``task_failed`` JSON line) and
restarted (the request answered); the TCP server's thread or the drives' event
loop dying ends the command at once with exit status 1 and one line, not a
silent simulator that answers nothing until its ``--duration``."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

import pytest
from cli_helpers import ROOT, env

from pyrtu import pdu
from pyrtu.pdu.errors import ModbusError
from pyrtu.tcp import TcpClient
from pyrtu.vbus import VirtualBus

BAUD = 38400
#: a safety net: each run ends on its own well before
PATIENCE = 60.0

#: patches (run before the command line), by name
PATCHES = {
    # a TCP server task's fault: its bus worker's first take raises, at the start (a
    # request that comes before the restart waits in the queue for it)
    "task": """\
from pyrtu.gateway._plan import FairQueue
real, calls = FairQueue.pop, [0]
def pop(self):
    calls[0] += 1
    if calls[0] == 1:
        raise KeyError("injected")
    return real(self)
FairQueue.pop = pop
""",
    # the TCP server's thread dies: a SystemExit out of its loop (the first request)
    "tcp-thread": """\
from pyrtu.tcp.server import LocalBus
def transact_now(self, slave, pdu):
    raise SystemExit("injected")
LocalBus.transact_now = transact_now
""",
    # the drives' event loop dies a moment after it started serving
    "drive-loop": """\
from pyrtu.cli._simulate_many import DriveLoop
real = DriveLoop.start
def start(self):
    real(self)
    def die():
        raise SystemExit("injected")
    self._thread.loop.call_soon_threadsafe(self._thread.loop.call_later, 0.3, die)
DriveLoop.start = start
""",
}

WRAPPER = "{patch}\nimport sys\nfrom pyrtu.cli import main\nsys.exit(main(sys.argv[1:]))\n"


def simulate(patch: str, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", WRAPPER.format(patch=PATCHES[patch]), "simulate", *args],
        cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def ready(
    proc: subprocess.Popen[str], before: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    """The ``ready`` line's document; the lines before it go to ``before`` (none
    expected unless it is given)."""
    assert proc.stdout is not None
    while True:
        line = proc.stdout.readline()
        assert line, proc.communicate(timeout=PATIENCE)[1]
        doc: dict[str, Any] = json.loads(line)
        if doc["type"] == "ready":
            return doc
        assert before is not None, doc
        before.append(doc)


def test_a_tcp_server_task_that_raises_is_reported_and_restarted() -> None:
    proc = simulate("task", "cfw100", "--tcp", "127.0.0.1:0", "--duration", "3", "--json")
    docs: list[dict[str, Any]] = []
    try:
        url = f"tcp://{ready(proc, docs)['tcp']}"
        with TcpClient(url, timeout=10.0) as client:
            got = client.request(1, pdu.read_request(3, 683, 1))  # answered after the restart
            assert got is not None and len(pdu.parse_registers(got, 1)) == 1
        out, err = proc.communicate(timeout=PATIENCE)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    docs += [json.loads(line) for line in out.splitlines()]
    (event,) = [d for d in docs if d.get("type") == "task_failed"]
    assert event["task"] == "pyrtu-gateway-bus-0" and event["error"] == "KeyError: 'injected'"
    (line,) = [ln for ln in err.splitlines() if "task" in ln]
    assert line.startswith(
        "pyrtu simulate: task pyrtu-gateway-bus-0 failed: KeyError: 'injected' (restarting in "
    )
    assert "Traceback" not in err


def test_the_tcp_server_thread_dying_ends_the_command_with_status_1() -> None:
    proc = simulate("tcp-thread", "cfw100", "--tcp", "127.0.0.1:0", "--duration", "30", "--json")
    try:
        url = f"tcp://{ready(proc)['tcp']}"
        started = time.monotonic()
        with TcpClient(url, timeout=5.0) as client, pytest.raises((ModbusError, OSError)):
            client.request(1, pdu.read_request(3, 683, 1))  # the request that kills it
        out, err = proc.communicate(timeout=PATIENCE)
        took = time.monotonic() - started
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 1, err
    assert took < 20, "it ran on to its --duration"  # it ends at once, not after 30 s
    (line,) = [ln for ln in err.splitlines() if "internal error" in ln]
    assert line == (
        "pyrtu simulate: internal error: the TCP server stopped: SystemExit: injected; "
        "nothing answers any more"
    )
    (doc,) = [json.loads(x) for x in out.splitlines() if '"exit_code"' in x]
    assert doc["exit_code"] == 1 and doc["error"] == "failure"
    assert "Traceback" not in err


def test_the_drives_event_loop_dying_ends_the_command_with_status_1() -> None:
    with (
        VirtualBus(2, baudrate=BAUD, parity="N") as a,
        VirtualBus(2, baudrate=BAUD, parity="N") as b,
    ):
        started = time.monotonic()
        proc = simulate("drive-loop", "cfw701", "-p", a.paths[1], "-p", b.paths[1],
                        "--baudrate", str(BAUD), "--parity", "N", "--duration", "30")  # fmt: skip
        try:
            _out, err = proc.communicate(timeout=PATIENCE)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        took = time.monotonic() - started
    assert proc.returncode == 1, err
    assert took < 20, "it ran on to its --duration"
    (line,) = [ln for ln in err.splitlines() if "internal error" in ln]
    assert line == (
        "pyrtu simulate: internal error: the drives' event loop stopped: SystemExit: injected; "
        "nothing answers any more"
    )
    assert "Traceback" not in err, err
