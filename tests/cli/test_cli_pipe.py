"""The long-running commands end quietly, with status 0, when the reader of their
stdout goes away (``| head -1``) even when they have nothing more to write: a real
pipe into a real ``head``, the commands as subprocesses."""

from __future__ import annotations

import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import ROOT, env
from peers.tools import free_tcp_port

PY = f"{shlex.quote(sys.executable)} -m pyrtu"


def through_head(command: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    """``command | head -1`` with pipefail: the command's own exit status counts.
    The timeout only catches a command that never ends (it has nothing more to
    write after its first line, so only the pipe's closing can end it)."""
    return subprocess.run(
        ["bash", "-o", "pipefail", "-c", f"{PY} {command} | head -1"],
        cwd=ROOT,
        env=env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def with_output_closed(*args: str) -> subprocess.CompletedProcess[str]:
    """``python -m pyrtu ARGS`` whose stdout is a pipe closed before it starts (the race
    ``| head -1`` loses on a loaded machine, made certain)."""
    import os

    r, w = os.pipe()
    os.close(r)
    try:
        return subprocess.run(
            [sys.executable, "-m", "pyrtu", *args],
            cwd=ROOT,
            env=env(),
            stdout=w,
            stderr=subprocess.PIPE,
            text=True,
            timeout=60,
        )
    finally:
        os.close(w)


@pytest.fixture
def tcp_drive() -> Iterator[int]:
    """A simulated CFW701 on Modbus TCP (the gateway's bus)."""
    port = free_tcp_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pyrtu",
            "simulate",
            "cfw701",
            "--tcp",
            f"127.0.0.1:{port}",
            "--json",
        ],
        cwd=ROOT,
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    assert proc.stdout is not None
    assert "ready" in proc.stdout.readline()  # its first JSON line: listening
    try:
        yield port
    finally:
        proc.terminate()
        proc.wait(10)


def test_vbus_with_its_output_already_closed(tmp_path: Path) -> None:
    """The reader is gone before the drops' paths are printed (the race ``| head -1``
    loses on a loaded machine, made certain): status 0, no error about --dir."""
    out = with_output_closed("vbus", "--drops", "2", "--dir", str(tmp_path / "b"))
    assert out.returncode == 0, out.stderr
    assert "--dir" not in out.stderr and "Traceback" not in out.stderr


def test_vbus(tmp_path: Path) -> None:
    r = through_head(f"vbus --drops 2 --dir {tmp_path / 'bus'}")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(tmp_path / "bus" / "drop0")
    assert "Traceback" not in r.stderr


def test_simulate() -> None:
    r = through_head(f"simulate cfw701 --tcp 127.0.0.1:{free_tcp_port()} --json")
    assert r.returncode == 0, r.stderr
    assert '"ready"' in r.stdout or "listen" in r.stdout
    assert "Traceback" not in r.stderr


def test_gateway(tcp_drive: int) -> None:
    bus = f"tcp://127.0.0.1:{tcp_drive}=1"
    r = through_head(f"gateway --listen 127.0.0.1:0 --port {bus} --json")
    assert r.returncode == 0, r.stderr
    assert '"ready"' in r.stdout
    assert "Traceback" not in r.stderr


def test_demo() -> None:
    """The demo ends quietly like every other command (it reported its own output's
    closed pipe as a failure, status 1: #27.14)."""
    r = through_head("demo --duration 2")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("pyrtu ") and "demo" in r.stdout
    assert "Broken pipe" not in r.stderr and "Traceback" not in r.stderr


def test_demo_with_its_output_already_closed() -> None:
    out = with_output_closed("demo", "--duration", "2")
    assert out.returncode == 0, out.stderr
    assert "Broken pipe" not in out.stderr and "Traceback" not in out.stderr
