"""``pyrtu sniff --capture FIFO`` ends on SIGTERM and SIGINT while it waits for a
writer (blocked in open) or for bytes from a silent one (blocked in read): a real
FIFO, a real ``python -m pyrtu`` and a real signal."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import ROOT, env


def sniff_fifo(fifo: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "sniff", "--capture", str(fifo)],
        cwd=ROOT,
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def blocked_on_the_fifo(proc: subprocess.Popen[str], fifo: Path, timeout: float = 60.0) -> None:
    """Wait until the command sleeps in the FIFO: in open() waiting for a writer
    (the kernel's wchan ``wait_for_partner``) or in read() with the FIFO open (its
    descriptor in /proc/PID/fd), so that the signal finds its handlers installed
    (a signal during the interpreter's start-up would prove nothing)."""
    deadline = time.monotonic() + timeout
    target = str(fifo)
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        try:
            wchan = Path(f"/proc/{proc.pid}/wchan").read_text()
            fds = [
                os.readlink(f"/proc/{proc.pid}/fd/{fd}")
                for fd in os.listdir(f"/proc/{proc.pid}/fd")
            ]
        except OSError:
            fds, wchan = [], ""
        if wchan == "wait_for_partner" or (target in fds and "pipe" in wchan):
            return
        time.sleep(0.02)
    pytest.fail(f"sniff never blocked on {fifo} (wchan {wchan!r})")


def stopped_by(
    proc: subprocess.Popen[str], fifo: Path, sig: signal.Signals
) -> tuple[int, str, str]:
    blocked_on_the_fifo(proc, fifo)
    proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"sniff --capture FIFO ignored {sig.name}")
    return proc.returncode, out, err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_no_writer_yet(tmp_path: Path, sig: signal.Signals) -> None:
    fifo = tmp_path / "bus.fifo"
    os.mkfifo(fifo)
    code, out, err = stopped_by(sniff_fifo(fifo), fifo, sig)
    assert code == 0, err
    assert "0 frames" in out and "Traceback" not in err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_silent_writer(tmp_path: Path, sig: signal.Signals) -> None:
    fifo = tmp_path / "bus.fifo"
    os.mkfifo(fifo)
    proc = sniff_fifo(fifo)
    writer = os.open(fifo, os.O_WRONLY)  # meets the reader's open; then writes nothing
    try:
        code, out, err = stopped_by(proc, fifo, sig)
    finally:
        os.close(writer)
    assert code == 0, err
    assert "0 frames" in out and "Traceback" not in err
