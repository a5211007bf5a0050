"""``pyrtu gateway`` as a program: usage errors (exit 2, naming the flag), and a run
with a libmodbus TCP server as its bus (the serial buses: test_gateway_serial.py)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from peers import pattern
from peers.tools import (
    PeerBinaries,
    free_tcp_port,
    libmodbus_server,
    peer_env,
    pyrtu_slave_process,
)

from pyrtu import ExceptionResponseError, pdu
from pyrtu import gateway as gateways
from pyrtu.tcp import TcpClient

pytest_plugins = ["peers.fixtures"]


def pyrtu(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", "gateway", *args],
        capture_output=True, text=True, timeout=60, env=peer_env(), check=False,
    )  # fmt: skip


def start_gateway(*args: str) -> subprocess.Popen[str]:
    """``pyrtu gateway --listen 127.0.0.1:0 ARGS`` running, its stdout and stderr piped."""
    return subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "gateway", "--listen", "127.0.0.1:0", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip


def stop_gateway(proc: subprocess.Popen[str], timeout: float = 15.0) -> tuple[str, str]:
    """SIGTERM, as a service manager ends it; what it wrote (stdout, stderr)."""
    proc.send_signal(signal.SIGTERM)
    return proc.communicate(timeout=timeout)


def kill_gateway(proc: subprocess.Popen[str]) -> None:
    """The gateway gone, whatever a test did (its ``finally``)."""
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)


def served_again(c: TcpClient, unit: int, request: bytes, on_refused: Callable[[], None]) -> bytes:
    """``request`` to ``unit`` repeated while the gateway answers 0x0A (its bus is not
    back yet; ``on_refused`` after each, within 60 s): the first answer."""
    import time

    end = time.monotonic() + 60.0
    while True:
        try:
            return c.request(unit, request) or b""
        except ExceptionResponseError as exc:
            assert exc.code == 0x0A and time.monotonic() < end
            on_refused()


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--listen", "nope", "--port", "x"], "--listen"),
        (["--listen", "127.0.0.1:70000", "--port", "x"], "--listen"),
        (["--listen", "127.0.0.1:0", "--port", "x=1-300"], "--port"),
        (["--listen", "127.0.0.1:0", "--port", "x=a"], "--port"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--port", "b"], "--port"),
        (["--listen", "127.0.0.1:0", "--port", "a=1-5", "--port", "b=5"], "unit id 5"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--max-queue", "0"], "--max-queue"),
        (
            ["--listen", "127.0.0.1:0", "--port", "a", "--max-connections", "-1"],
            "--max-connections",
        ),
        (["--listen", "127.0.0.1:0", "--port", "a", "--max-bus-queue", "x"], "--max-bus-queue"),
        (
            ["--listen", "127.0.0.1:0", "--port", "a", "--max-write-buffer", "1.5"],
            "--max-write-buffer",
        ),
        (["--listen", "127.0.0.1:0", "--port", "a", "--listen-rtu", "host"], "--listen-rtu"),
        (
            ["--listen", "127.0.0.1:0", "--port", "a", "--broadcast-delay", "-1"],
            "--broadcast-delay",
        ),
        # the same port twice is a usage error, not "busy: another program holds it"
        (["--listen", "127.0.0.1:0", "--port", "x=1-10", "--port", "x=11-20"], "--port: x"),
        (["--listen", "127.0.0.1:0", "--port", "x=1", "--port", "./x=2"], "given twice"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--header-timeout", "-1"], "--header-timeout"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--idle-timeout", "x"], "--idle-timeout"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--unit-map", "256=1"], "--unit-map"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--unit-map", "255=0"], "--unit-map"),
        (["--listen", "127.0.0.1:0", "--port", "a", "--unit-map", "255"], "--unit-map"),
        (["--listen", "127.0.0.1:0", "--port", "a=1-5", "--unit-map", "255=9"], "--unit-map"),
        (["--listen", "127.0.0.1:0", "--port", "a=1-5", "--unit-map", "3=1"], "--unit-map"),
    ],
)
def test_usage_errors(args: list[str], flag: str) -> None:
    done = pyrtu(*args)
    assert done.returncode == 2, done.stderr
    assert flag in done.stderr and "Traceback" not in done.stderr


def test_help_documents_the_limits_and_their_defaults() -> None:
    """The defaults --help gives are the library's (pyrtu.gateway), for every limit."""
    done = pyrtu("--help")
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    for flag, default in (
        ("--max-connections", gateways.MAX_CONNECTIONS),
        ("--max-queue", gateways.MAX_QUEUED_PER_CONNECTION),
        ("--max-bus-queue", gateways.MAX_QUEUED_PER_BUS),
        ("--max-write-buffer", gateways.MAX_WRITE_BUFFER),
    ):
        # the option's own help (after its metavar), and the summary in the description
        assert re.search(rf"{flag} (N|BYTES) [^-]{{0,80}}\(default {default}\)", text), flag
        assert f"{flag} {default}" in text
    limits = gateways.GatewayLimits()
    assert (limits.max_connections, limits.max_write_buffer) == (64, 256 * 1024)
    for flag, seconds in (
        ("--header-timeout", gateways.HEADER_TIMEOUT),
        ("--idle-timeout", gateways.IDLE_TIMEOUT),
    ):
        assert re.search(rf"{flag} SECONDS [^-]{{0,80}}\(0: no limit; default {seconds:g}\)", text)
        assert f"{flag} {seconds:g} s" in text
    assert "--unit-map" in text and "255=1,0=1" in text


def test_a_port_missing_at_start_is_served_when_it_comes(tmp_path: Path) -> None:
    """Started with one bus on the virtual bus and one whose port is not there yet (an
    adapter that appears after boot): the gateway starts, says once that the port is
    missing, serves the other bus, answers 0x0A for the missing one (path
    unavailable, [AP] 7), and serves it once the port appears (a link to a drop of
    a second virtual bus, made while it runs)."""
    import time

    vbus = pytest.importorskip("pyrtu.vbus")
    missing = tmp_path / "ttyUSB1"
    read = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 3, 2)
    with (
        vbus.VirtualBus(2, baudrate=115200, parity="N") as first,
        vbus.VirtualBus(2, baudrate=115200, parity="N") as second,
        pyrtu_slave_process(first.paths[1], 1),
        pyrtu_slave_process(second.paths[1], 2),
    ):
        proc = start_gateway(
            "--port", f"{first.paths[0]}=1", "--port", f"{missing}=2", "--baudrate", "115200",
            "--parity", "N", "--timeout", "0.5", "--json",
        )  # fmt: skip
        try:
            assert proc.stdout is not None
            lines = [json.loads(proc.stdout.readline())]
            while lines[-1]["type"] != "ready":
                lines.append(json.loads(proc.stdout.readline()))
            with TcpClient(f"tcp://{lines[-1]['listen']}", timeout=5.0) as c:
                got = c.request(1, read)
                assert pdu.parse_registers(got or b"", 2) == pattern.holdings(1, 3, 2)
                with pytest.raises(ExceptionResponseError) as info:
                    c.request(2, read)
                assert info.value.code == 0x0A
                time.sleep(1.0)  # reopening attempts that fail: not reported again
                os.symlink(second.paths[0], missing)
                got = served_again(c, 2, read, lambda: time.sleep(0.05))
                assert pdu.parse_registers(got, 2) == pattern.holdings(2, 3, 2)
                got = c.request(1, read)
                assert pdu.parse_registers(got or b"", 2) == pattern.holdings(1, 3, 2)
            out, err = stop_gateway(proc)
        finally:
            kill_gateway(proc)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    lines += [json.loads(line) for line in out.splitlines()]
    events = [(e["bus"], e["up"], e["starting"]) for e in lines if e["type"] == "bus"]
    assert events == [(str(missing), False, True), (str(missing), True, False)], lines
    assert "No such file" in lines[0]["error"]
    stopped = lines[-1]
    assert (stopped["bus_failures"], stopped["bus_recoveries"]) == (1, 1)
    assert stopped["bus_down"] == [False, False]


def test_a_port_missing_at_start_is_said_once_in_words() -> None:
    done = pyrtu("--listen", "127.0.0.1:0", "--port", "/dev/does-not-exist", "--duration", "1.5")
    assert done.returncode == 0, done.stderr
    said = [line for line in done.stderr.splitlines() if "/dev/does-not-exist" in line]
    assert said[0].startswith("pyrtu gateway: bus /dev/does-not-exist is not available: ")
    assert "0x0A" in said[0] and "Traceback" not in done.stderr
    assert sum("is not available" in line for line in said) == 1  # retried, said once
    assert "1 bus failures, 0 recovered" in done.stderr


@pytest.fixture
def gateway_process(peer_binaries: PeerBinaries) -> Iterator[tuple[subprocess.Popen[str], str]]:
    port = free_tcp_port()
    with libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1):
        proc = start_gateway("--port", f"tcp://127.0.0.1:{port}=1-9", "--json", "--timeout", "0.5")
        assert proc.stdout is not None
        ready = json.loads(proc.stdout.readline())
        assert ready["type"] == "ready"
        try:
            yield proc, f"tcp://{ready['listen']}"
        finally:
            kill_gateway(proc)


def test_gateway_runs_and_reports(gateway_process: tuple[subprocess.Popen[str], str]) -> None:
    proc, url = gateway_process
    with TcpClient(url, timeout=2.0) as c:
        got = c.request(1, pdu.read_request(pdu.READ_INPUT_REGISTERS, 5, 3))
        assert got is not None and pdu.parse_registers(got, 3) == pattern.inputs(1, 5, 3)
        with pytest.raises(ExceptionResponseError) as info:
            c.request(10, pdu.read_request(pdu.READ_INPUT_REGISTERS, 5, 3))
        assert info.value.code == 0x0A
    out, err = stop_gateway(proc, timeout=10)
    assert proc.returncode == 0, err
    stopped = json.loads(out.splitlines()[-1])
    assert stopped["type"] == "stopped"
    assert (stopped["requests"], stopped["answers"], stopped["no_route"]) == (2, 1, 1)


def test_unit_map_sends_0xff_and_0_to_a_slave_and_the_summary_counts(
    peer_binaries: PeerBinaries,
) -> None:
    """--unit-map 255=1,0=1: libmodbus's default unit 0xFF and unit 0 (Messaging on
    TCP/IP Implementation Guide 4.4.1.2) reach slave 1 and are answered under their
    own unit id; the summary line counts what it says."""
    import socket
    import struct

    from pyrtu import encode_mbap, parse_tcp_stream

    port = free_tcp_port()
    with libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1):
        proc = start_gateway(
            "--port", f"tcp://127.0.0.1:{port}=1-9", "--unit-map", "255=1,0=1", "--timeout", "0.5"
        )  # fmt: skip
        try:
            assert proc.stderr is not None
            line = proc.stderr.readline()
            m = re.search(r"listening on ([\d.]+):(\d+)", line)
            assert m, line
            read = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 7, 2)
            with socket.create_connection((m.group(1), int(m.group(2))), timeout=5) as s:
                for tid, unit in ((1, 0xFF), (2, 0), (3, 1), (4, 10)):
                    s.sendall(encode_mbap(tid, unit, read))
                    head = b""
                    while len(head) < 6:
                        head += s.recv(6 - len(head))
                    (length,) = struct.unpack(">H", head[4:])
                    body = b""
                    while len(body) < length:
                        body += s.recv(length - len(body))
                    (frame,) = parse_tcp_stream(head + body, "master")
                    assert (frame.transaction, frame.unit) == (tid, unit)
                    if unit == 10:
                        assert frame.exception_code == 0x0A
                    else:
                        assert pdu.parse_registers(frame.pdu, 2) == pattern.holdings(1, 7, 2)
            _, err = stop_gateway(proc, timeout=10)
        finally:
            kill_gateway(proc)
    assert proc.returncode == 0, err
    assert "4 requests, 3 answers, 1 exceptions" in err
    assert "1 no route, 0 bus unavailable" in err and "0 bus failures" in err


@pytest.mark.parametrize("json_lines", [True, False])
def test_a_bus_that_goes_away_is_reported_once_and_reopened(
    peer_binaries: PeerBinaries, json_lines: bool
) -> None:
    """The TCP server behind a --port stops: reported once (a JSON "bus" line, or one
    line on stderr), 0x0A for its requests (counted as bus unavailable, not no
    route); it starts again on the same port: the gateway reconnects on its back-off
    schedule (0.5 s doubling), says so once, and serves."""
    import time

    port = free_tcp_port()
    read = pdu.read_request(pdu.READ_HOLDING_REGISTERS, 3, 2)
    first = libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1).start()
    proc = start_gateway(
        "--port", f"tcp://127.0.0.1:{port}=1-9", "--timeout", "0.5",
        *(["--json"] if json_lines else []),
    )  # fmt: skip
    second = None
    try:
        if json_lines:
            assert proc.stdout is not None
            listen = json.loads(proc.stdout.readline())["listen"]
        else:
            assert proc.stderr is not None
            m = re.search(r"listening on (\S+:\d+),", proc.stderr.readline())
            assert m is not None
            listen = m.group(1)
        with TcpClient(f"tcp://{listen}", timeout=5.0) as c:
            assert pdu.parse_registers(c.request(1, read) or b"", 2) == pattern.holdings(1, 3, 2)
            first.stop()
            refused = 0
            for _ in range(10):
                with pytest.raises(ExceptionResponseError) as info:
                    c.request(1, read)
                assert info.value.code == 0x0A
                refused += 1
            second = libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1).start()

            def refused_again() -> None:
                nonlocal refused
                refused += 1
                time.sleep(0.1)

            got = served_again(c, 1, read, refused_again)
            assert pdu.parse_registers(got, 2) == pattern.holdings(1, 3, 2)
        out, err = stop_gateway(proc)
    finally:
        kill_gateway(proc)
        first.stop()
        if second is not None:
            second.stop()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    where = f"tcp://127.0.0.1:{port}"
    if not json_lines:
        failed = [line for line in err.splitlines() if "failed" in line]
        back = [line for line in err.splitlines() if "is back after" in line]
        assert len(failed) == 1 and where in failed[0] and "0x0A" in failed[0], err
        assert len(back) == 1 and where in back[0], err
        assert f"{refused} bus unavailable); 1 bus failures, 1 recovered" in err, err
        return
    lines = [json.loads(line) for line in out.splitlines()]
    events = [(e["bus"], e["up"]) for e in lines if e["type"] == "bus"]
    assert events == [(where, False), (where, True)], out
    stopped = lines[-1]
    assert (stopped["bus_failures"], stopped["bus_recoveries"]) == (1, 1)
    assert stopped["bus_unavailable"] == refused and stopped["no_route"] == 0
    assert stopped["bus_down"] == [False]


def test_64_silent_connections_do_not_lock_the_command_out(
    gateway_process: tuple[subprocess.Popen[str], str],
) -> None:
    """The reported lock-out, on the command with its defaults: 64 connections that
    send nothing, drip one byte, or half a header take every --max-connections slot;
    a client that talks is still served (a silent one gives way), and the summary
    counts the evictions."""
    import socket

    from pyrtu import encode_mbap

    proc, url = gateway_process
    host, _, port = url[6:].rpartition(":")
    request = encode_mbap(1, 1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 2))
    silent = []
    try:
        for i in range(64):
            s = socket.create_connection((host, int(port)), timeout=5)
            if i % 3:
                s.sendall(request[: 1 if i % 3 == 1 else 3])
            silent.append(s)
        for _ in range(3):
            with TcpClient(url, timeout=5.0) as c:
                got = c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 2))
                assert pdu.parse_registers(got or b"", 2) == pattern.holdings(1, 0, 2)
    finally:
        for s in silent:
            s.close()
    out, err = stop_gateway(proc, timeout=10)
    assert proc.returncode == 0, err
    stopped = json.loads(out.splitlines()[-1])
    assert stopped["evicted"] >= 1 and stopped["refused"] == 0
    assert stopped["answers"] == 3
