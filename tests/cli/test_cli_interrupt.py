"""Ctrl-C while a command starts ends it quietly with status 130 (#27.14): SIGINT is
sent at several moments of the start-up of several commands — while the package
imports (its first module, the C core, the drivers), while the command line imports
its commands, while the arguments are parsed, and while the command connects and
waits — and no traceback, no ``KeyboardInterrupt``, reaches the user.

The moments are found without touching the command: ``python -X importtime`` makes
the interpreter itself write one line on stderr as each module's import completes,
and the signal is sent as soon as the chosen line is seen.  (What Python does
before it imports pyrtu, its own start and ``site``, is out of pyrtu's reach.)
"""

from __future__ import annotations

import re
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import ROOT, env

#: modules whose import completing marks a moment of the start-up, in order
MOMENTS = [
    "pyrtu._startup",  # the package's first module: the earliest pyrtu can act
    "pyrtu.core._backend",  # the C core (or its twin) loaded
    "pyrtu.drivers.master",  # deep in the package's imports
    "pyrtu.cli.common",  # the command line importing its commands
    "pyrtu.cli.bridge",  # the last command registered
    "pyrtu.cli",  # the command line imported: the arguments are parsed next
]


@pytest.fixture
def silent_server() -> Iterator[int]:
    """A Modbus TCP port that accepts connections and never answers."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    accepted: list[socket.socket] = []
    stop = threading.Event()

    def serve() -> None:
        listener.settimeout(0.1)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                continue
            accepted.append(conn)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield listener.getsockname()[1]
    finally:
        stop.set()
        thread.join(5)
        for conn in accepted:
            conn.close()
        listener.close()


def interrupt_at(args: list[str], marker: str | None, after: float = 0.0) -> tuple[int, str]:
    """Run ``python -X importtime -m pyrtu ARGS``, send SIGINT when ``marker``'s import
    completed (None: when the command line's did) plus ``after`` seconds;
    (exit status, stderr without the import-time lines)."""
    proc = subprocess.Popen(
        [sys.executable, "-X", "importtime", "-m", "pyrtu", *args],
        cwd=ROOT,
        env=env(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stderr is not None and proc.stdout is not None
    want = re.compile(rb"\|\s+" + re.escape(marker or "pyrtu.cli").encode() + rb"\n")
    err = bytearray()
    selector = selectors.DefaultSelector()
    selector.register(proc.stderr, selectors.EVENT_READ)
    sent = False
    deadline = time.monotonic() + 60
    try:
        while not sent and time.monotonic() < deadline:
            if selector.select(0.5):
                chunk = proc.stderr.read1(65536)  # type: ignore[attr-defined]
                if not chunk:
                    break
                err += chunk
                if want.search(err):
                    time.sleep(after)
                    if proc.poll() is not None:  # it ended before the signal: no moment
                        proc.communicate(timeout=30)
                        return MISSED, err.decode("utf-8", "replace")
                    proc.send_signal(signal.SIGINT)
                    sent = True
        assert sent, f"{marker} was never imported: {err.decode()[-2000:]}"
        _stdout, rest = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    text = (err + rest).decode("utf-8", "replace")
    lines = [line for line in text.splitlines() if not line.startswith("import time:")]
    return proc.returncode, "\n".join(lines)


#: interrupt_at's status when the command had ended before the signal could be sent
#: (a command that fails at once, read by a test process that a loaded machine slows)
MISSED = -1


def interrupted(args: list[str], marker: str, tries: int = 5) -> tuple[int, str]:
    """`interrupt_at`, again while the signal came too late to find the command."""
    for _ in range(tries):
        code, err = interrupt_at(args, marker)
        if code != MISSED:
            return code, err
    pytest.fail(f"{args}: ended before SIGINT could be sent, {tries} times: {err[-2000:]}")


COMMANDS = [
    ["read", "/nonexistent/ttyX", "0"],
    ["vbus", "--drops", "2", "--duration", "5"],
    ["demo", "--duration", "5"],
    ["--help"],
]


@pytest.mark.parametrize("marker", MOMENTS)
@pytest.mark.parametrize("args", COMMANDS, ids=[c[0] for c in COMMANDS])
def test_ctrl_c_while_the_command_imports(args: list[str], marker: str) -> None:
    code, err = interrupted(args, marker)
    assert code == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


def test_ctrl_c_while_the_poller_starts(tmp_path: Path, silent_server: int) -> None:
    config = tmp_path / "points.toml"
    config.write_text(
        f'[[bus]]\nname = "t"\nport = "tcp://127.0.0.1:{silent_server}"\ntimeout = 5\n\n'
        '[[point]]\nname = "x"\nbus = "t"\nslave = 1\ntable = "holding"\naddress = 0\n'
    )
    for marker in MOMENTS:
        code, err = interrupt_at(["poll", "--config", str(config), "--json"], marker)
        assert code == 130, (marker, err)
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, (marker, err)


@pytest.mark.parametrize("after", [0.0, 0.3, 1.0])
def test_ctrl_c_while_a_command_connects_and_waits(silent_server: int, after: float) -> None:
    """Parsing, connecting, waiting for the answer (timeout 5 s): each ends at once,
    with status 130 and at most the one-line "interrupted" of a one-shot command."""
    port = f"tcp://127.0.0.1:{silent_server}"
    code, err = interrupt_at(["read", port, "0", "--timeout", "5"], None, after)
    assert code == 130, err  # not 4: the timeout did not end it
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert len(err.strip().splitlines()) <= 1, err


def test_ctrl_c_inside_a_callback_whose_exceptions_python_ignores_still_ends() -> None:
    """The start-up's SIGINT handler can run inside a weakref callback (the import
    system's module locks have one) or a ``__del__``, where Python prints an exception
    and goes on: the command must end there all the same, status 130, quietly (CI saw
    ``pyrtu vbus`` run on after "Exception ignored in: ... _get_module_lock ... cb")."""
    code = (
        "import os, signal, sys, time, weakref\n"
        "sys.argv = ['pyrtu']  # this process is the command (pyrtu._startup.is_the_command)\n"
        "import pyrtu._startup\n"
        "class Lock: pass\n"
        "def callback(_ref):\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(0.5)  # the handler runs here, inside the callback\n"
        "lock = Lock()\n"
        "ref = weakref.ref(lock, callback)\n"
        "del lock\n"
        "print('went on')\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env(), timeout=30
    )
    assert r.returncode == 130, (r.stdout, r.stderr)
    assert "went on" not in r.stdout and "Traceback" not in r.stderr, r.stderr
