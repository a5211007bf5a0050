"""``pyrtu simulate DEVICE --tcp HOST:PORT``: a simulated drive over Modbus TCP, alone
or on its serial port and TCP at once (one drive, one DataStore)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator

import pytest
from peers.tools import peer_env

from pyrtu import ExceptionResponseError, Master, pdu
from pyrtu.tcp import TcpClient

pytest_plugins = ["peers.fixtures"]


def start(*args: str) -> tuple[subprocess.Popen[str], dict[str, object]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "simulate", *args, "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line, proc.stderr.read() if proc.stderr else ""
    return proc, json.loads(line)


def stop(proc: subprocess.Popen[str]) -> dict[str, object]:
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=15)
    assert proc.returncode == 0, err
    doc: dict[str, object] = json.loads(out.splitlines()[-1])
    return doc


@pytest.fixture
def cleanup() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.communicate()


def test_drive_over_tcp_only(cleanup: list[subprocess.Popen[str]]) -> None:
    proc, ready = start("cfw100", "--tcp", "127.0.0.1:0")
    cleanup.append(proc)
    assert ready["type"] == "ready" and ready["port"] is None
    with TcpClient(f"tcp://{ready['tcp']}", timeout=2.0) as c:
        got = c.request(1, pdu.device_id_request(1, 0))
        assert got is not None and pdu.parse_device_id(got, 1).objects[0] == (0, b"WEG")
        c.request(1, pdu.write_register_request(683, 2048))  # speed reference P683
        got = c.request(1, pdu.read_request(3, 683, 1))
        assert got is not None and pdu.parse_registers(got, 1) == [2048]
        with pytest.raises(ExceptionResponseError) as info:
            c.request(1, pdu.read_request(3, 9999, 1))
        assert info.value.code == 2  # as the manual's example
    stopped = stop(proc)
    assert stopped["counters"]["requests"] == 4  # type: ignore[index]


def test_drive_on_serial_and_tcp(
    pty_pair: tuple[str, str], cleanup: list[subprocess.Popen[str]]
) -> None:
    master_side, drive_side = pty_pair
    proc, ready = start("cfw701", "--port", drive_side, "--parity", "N", "--baudrate", "115200",
                        "--t35", "0", "--tcp", "127.0.0.1:0")  # fmt: skip
    cleanup.append(proc)
    with Master(master_side, baudrate=115200, parity="N", t35=0, timeout=1.0) as serial_m:
        with Master(f"tcp://{ready['tcp']}", timeout=2.0) as tcp_m:
            serial_m.write_register(1, 683, 1000)
            assert tcp_m.read_holding_registers(1, 683, 1) == [1000]
            tcp_m.write_register(1, 683, 3000)
            assert serial_m.read_holding_registers(1, 683, 1) == [3000]
    stop(proc)


def test_simulate_needs_a_port_or_tcp() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "pyrtu", "simulate", "cfw100"],
        capture_output=True, text=True, env=peer_env(), timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "--tcp" in done.stderr and "Traceback" not in done.stderr
    done = subprocess.run(
        [sys.executable, "-m", "pyrtu", "simulate", "cfw100", "--tcp", "nohost"],
        capture_output=True, text=True, env=peer_env(), timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 2 and "--tcp" in done.stderr
