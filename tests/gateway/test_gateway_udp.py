"""``pyrtu gateway`` and Modbus over UDP: ``--udp-listen HOST:PORT`` (clients over UDP,
beside the TCP listener) and ``--port udp://HOST:PORT=UNITS`` (a bus that is a Modbus
over UDP server: pymodbus's ``ModbusUdpServer``, an independent peer serving
`peers.pattern`)."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest
from peers import pattern
from peers.tools import peer_env, pymodbus_server

from pyrtu import Master, pdu

TIMEOUT = 2.0


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def gateway(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "gateway", "--listen", "127.0.0.1:0", *args, "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", "gateway", *args],
        capture_output=True, text=True, timeout=60, env=peer_env(), check=False,
    )  # fmt: skip


@pytest.fixture(scope="module")
def udp_bus() -> Iterator[int]:
    """pymodbus's UDP server, slave 1: its port."""
    port = free_udp_port()
    with pymodbus_server(f"127.0.0.1:{port}", 1, mode="udp"):
        yield port


def test_udp_clients_through_a_udp_bus(udp_bus: int) -> None:
    proc = gateway(
        "--udp-listen", "127.0.0.1:0", "--port", f"udp://127.0.0.1:{udp_bus}=1",
        "--timeout", str(TIMEOUT),
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        ready = json.loads(proc.stdout.readline())
        assert ready["type"] == "ready" and ready["buses"] == [f"udp://127.0.0.1:{udp_bus}"]
        with (
            Master(f"udp://{ready['listen_udp']}", timeout=TIMEOUT) as over_udp,
            Master(f"tcp://{ready['listen']}", timeout=TIMEOUT) as over_tcp,
        ):
            assert over_udp.read_holding_registers(1, 10, 5) == pattern.holdings(1, 10, 5)
            assert over_tcp.read_input_registers(1, 3, 2) == pattern.inputs(1, 3, 2)
            over_udp.write_register(1, 700, 4242)
            assert over_tcp.read_holding_registers(1, 700, 1) == [4242]
            for request in (pdu.read_request(1, 0, 20), bytes([3, 0xEA, 0x60, 0, 1])):
                assert over_udp.exchange(1, request) == over_tcp.exchange(1, request)
            answer = over_udp.exchange(7, pdu.read_request(3, 0, 1))  # no bus carries 7
            assert answer == bytes([0x83, 0x0A])
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=15)
        assert proc.returncode == 0, err
        stopped = json.loads(out.splitlines()[-1])
        assert stopped["requests"] == 9 and stopped["connections"] == 2, stopped
        assert stopped["bad_datagrams"] == 0 and stopped["no_route"] == 1
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=10)


def test_usage_and_port_errors_name_their_flag() -> None:
    r = run("--listen", "127.0.0.1:0", "--udp-listen", "nope", "--port", "x")
    assert r.returncode == 2
    assert "--udp-listen" in r.stderr and "Traceback" not in r.stderr
    for bus, words in (
        ("udp://plc:99999=1", "'udp://plc:99999': the port must be 0..65535"),
        ("udp://=1", "'udp://': expected udp://HOST[:PORT]"),
        ("tcp://plc:99999=1", "'tcp://plc:99999': the port must be 0..65535"),
    ):
        r = run("--listen", "127.0.0.1:0", "--port", bus, "--duration", "1")
        assert r.returncode == 2, r.stderr
        assert f"argument -p/--port: {words}" in r.stderr and "Traceback" not in r.stderr
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        r = run(
            "--listen", "127.0.0.1:0", "--udp-listen", f"127.0.0.1:{port}",
            "--port", "udp://127.0.0.1:9=1", "--duration", "1",
        )  # fmt: skip
    assert r.returncode == 3, r.stderr
    assert "--udp-listen:" in r.stderr and "Traceback" not in r.stderr, r.stderr
