"""``pyrtu simulate DEVICE --udp HOST:PORT`` (Modbus over UDP, alone or beside
``--tcp``), read and written by the CLI's own ``udp://`` port, by pyrtu's master and by
pymodbus's ``ModbusUdpClient``; ``--read-only`` and ``--audit`` on the UDP listener;
the usage and port errors of ``--udp`` and of ``udp://`` ports."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest
from cli_helpers import pyrtu
from peers.tools import peer_env

from pyrtu import Master, pdu

TIMEOUT = 2.0


def start(*args: str) -> tuple[subprocess.Popen[str], dict[str, object]]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "simulate", *args, "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line, proc.stderr.read() if proc.stderr else ""
    return proc, json.loads(line)


def stop(proc: subprocess.Popen[str]) -> list[dict[str, object]]:
    """SIGTERM; the JSON lines it printed after "ready" (the last: "stopped")."""
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=15)
    assert proc.returncode == 0, err
    lines: list[dict[str, object]] = [json.loads(line) for line in out.splitlines()]
    assert lines[-1]["type"] == "stopped", lines
    return lines


@pytest.fixture
def cleanup() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    yield procs
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.communicate()


def test_a_drive_over_udp_only(cleanup: list[subprocess.Popen[str]]) -> None:
    from pymodbus.client import ModbusUdpClient

    proc, ready = start("cfw100", "--udp", "127.0.0.1:0")
    cleanup.append(proc)
    assert ready["type"] == "ready" and ready["tcp"] is None and ready["port"] is None
    url = f"udp://{ready['udp']}"
    with Master(url, timeout=TIMEOUT) as m:
        m.write_register(1, 683, 2048)  # the speed reference, P683
        assert m.read_holding_registers(1, 683, 1) == [2048]
        got = m.exchange(1, pdu.device_id_request(1, 0))
        assert pdu.parse_device_id(got, 1).objects[0] == (0, b"WEG")
    read = pyrtu("read", url, "683", "--timeout", TIMEOUT, "--json")
    assert read.code == 0, read.err
    assert read.json()["values"] == [2048]
    wrote = pyrtu("write", url, "683", "1024", "--timeout", TIMEOUT)
    assert wrote.code == 0, wrote.err
    host, _, port = str(ready["udp"]).rpartition(":")
    client = ModbusUdpClient(host, port=int(port), timeout=TIMEOUT, retries=0)
    try:
        assert client.connect()
        assert client.read_holding_registers(683, count=1, device_id=1).registers == [1024]
    finally:
        client.close()
    assert stop(proc)[-1]["counters"] == {"requests": 6, "responses": 6, "exceptions": 0}


def test_tcp_and_udp_serve_one_drive_read_only_and_audited(
    cleanup: list[subprocess.Popen[str]],
) -> None:
    proc, ready = start(
        "cfw100", "--tcp", "127.0.0.1:0", "--udp", "127.0.0.1:0", "--read-only", "--audit", "-"
    )
    cleanup.append(proc)
    udp, tcp = f"udp://{ready['udp']}", f"tcp://{ready['tcp']}"
    with Master(udp, timeout=TIMEOUT) as over_udp, Master(tcp, timeout=TIMEOUT) as over_tcp:
        for request in (pdu.read_request(3, 680, 2), pdu.read_request(3, 1, 3)):
            assert over_udp.exchange(1, request) == over_tcp.exchange(1, request)
    refused = pyrtu("write", udp, "683", "7", "--timeout", TIMEOUT)
    assert refused.code == 5 and "exception 1" in refused.err, refused.err
    lines = stop(proc)
    denied = [line for line in lines if line["type"] == "denied"]
    assert len(denied) == 1 and denied[0]["client"] == "127.0.0.1", lines
    assert denied[0]["kind"] == "read_only"
    assert lines[-1]["counters"] == {"requests": 5, "responses": 4, "exceptions": 1}


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--udp", "127.0.0.1:99999"], "--udp: expected HOST:PORT"),
        (["--udp", "nowhere"], "--udp: expected HOST:PORT"),
        (["--tcp", "127.0.0.1:20000-20001", "--udp", "127.0.0.1:0"], "--udp serves one device"),
        (
            ["--port", "/nonexistent/tty", "--read-only"],
            "--policy, --read-only and --audit go with --tcp or --udp",
        ),
        (["--udp", "127.0.0.1:0", "--tls-listen", "127.0.0.1:0"], "--tls-listen goes with --tcp"),
    ],
)
def test_usage_errors_of_udp(args: list[str], words: str) -> None:
    r = pyrtu("simulate", "cfw100", *args, "--duration", "1")
    assert r.code == 2 and words in r.err, r.err
    assert "Traceback" not in r.err


def test_a_udp_port_taken_is_a_port_error_naming_the_flag() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        r = pyrtu("simulate", "cfw100", "--udp", f"127.0.0.1:{port}", "--duration", "1")
    assert r.code == 3, r.err
    assert f"--udp: cannot listen on 127.0.0.1:{port}" in r.err and "Traceback" not in r.err


@pytest.mark.parametrize(
    ("url", "words"),
    [
        ("udp://", "'udp://': expected udp://HOST[:PORT]"),
        ("udp://plc:99999", "'udp://plc:99999': the port must be 0..65535"),
        ("udp://plc:502/x", "expected udp://HOST[:PORT]"),
    ],
)
def test_a_bad_udp_port_is_a_usage_error_before_anything_is_sent(url: str, words: str) -> None:
    for argv in (("read", url, "0"), ("write", url, "0", "1"), ("scan", url, "--range", "1-2")):
        r = pyrtu(*argv)
        assert r.code == 2, (argv, r.err)
        assert words in r.err and "Traceback" not in r.err, r.err


def test_scan_over_udp_and_a_closed_port() -> None:
    """``pyrtu scan udp://...`` finds the simulated drive (and says how it is reached);
    a port nothing is bound to is no answer (exit 4), said at once."""
    proc, ready = start("cfw100", "--udp", "127.0.0.1:0")
    try:
        r = pyrtu("scan", f"udp://{ready['udp']}", "--range", "1-3", "--timeout", TIMEOUT)
        assert r.code == 0, r.err
        assert "(Modbus over UDP, timeout 2000 ms" in r.out and "slave   1: answered" in r.out, (
            r.out
        )
        assert "1 slave found (1)" in r.out
    finally:
        stop(proc)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        free = s.getsockname()[1]
    r = pyrtu("read", f"udp://127.0.0.1:{free}", "0", "--timeout", TIMEOUT)
    assert r.code == 4 and "port unreachable" in r.err, r.err
