"""Other programs on the virtual bus: pyserial processes, pymodbus, minimalmodbus, the CLI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from pyrtu import add_crc
from pyrtu.vbus import VirtualBus, load_capture

ROOT = Path(__file__).resolve().parents[2]


def env() -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONPATH"] = str(ROOT) + os.pathsep + e.get("PYTHONPATH", "")
    return e


adu = add_crc  # the ADU of address + PDU, CRC low byte first (the core's own tests check it)


# A device in another process, plain pyserial: answers "read holding registers"
# requests for unit 7 with registers 100, 101, 102, ...
DEVICE = textwrap.dedent(
    """
    import sys, time
    import serial

    def crc16(data):
        crc = 0xFFFF
        for b in data:
            crc ^= b
            for _ in range(8):
                crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        return crc

    port = serial.Serial(sys.argv[1], 19200, timeout=0.005)
    print("ready", flush=True)
    buf = b""
    deadline = time.monotonic() + 10
    served = 0
    while served < int(sys.argv[2]) and time.monotonic() < deadline:
        buf += port.read(64)
        if len(buf) >= 8:
            req, buf = buf[:8], buf[8:]
            assert crc16(req) == 0, req.hex()
            unit, fc, addr, count = req[0], req[1], req[2] << 8 | req[3], req[4] << 8 | req[5]
            body = bytes([unit, fc, 2 * count])
            for i in range(count):
                body += (100 + addr + i).to_bytes(2, "big")
            crc = crc16(body)
            time.sleep(0.002)  # turnaround
            port.write(body + bytes((crc & 0xFF, crc >> 8)))
            served += 1
    print("served", served, flush=True)
    """
)


def test_pyserial_processes_on_separate_drops(tmp_path: Path) -> None:
    serial = pytest.importorskip("serial")
    cap = str(tmp_path / "interop.cap")
    with VirtualBus(3, baudrate=19200, capture=cap) as bus:
        dev = subprocess.Popen(
            [sys.executable, "-c", DEVICE, bus.paths[1], "3"],
            stdout=subprocess.PIPE,
            text=True,
            env=env(),
        )
        try:
            assert dev.stdout is not None
            assert dev.stdout.readline().strip() == "ready"
            assert bus.wait_clients(1)
            with (
                serial.Serial(bus.paths[0], 19200, timeout=1) as master,
                serial.Serial(bus.paths[2], 19200, timeout=0.2) as sniffer,
            ):
                assert bus.wait_clients(0) and bus.wait_clients(2)
                for addr in (0, 5, 10):
                    req = adu(bytes([7, 3, 0, addr, 0, 2]))
                    master.write(req)
                    resp = master.read(9)
                    assert resp == adu(bytes([7, 3, 4, 0, 100 + addr, 0, 101 + addr]))
                    assert sniffer.read(17) == req + resp  # a third drop hears both
            assert dev.stdout.readline().split() == ["served", "3"]
            assert dev.wait(5) == 0
        finally:
            if dev.poll() is None:
                dev.kill()
                dev.wait()
    records = load_capture(cap).records
    assert [r.drop for r in sorted(records, key=lambda r: r.t_us)] == [0, 1] * 3


# A pymodbus RTU server (slave) in another process.
PYMODBUS_SERVER = textwrap.dedent(
    """
    import sys
    from pymodbus.datastore import (
        ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext,
    )
    from pymodbus.server import StartSerialServer

    # protocol address N is block address N + 1 in pymodbus: register N = 1000 + N
    hr = ModbusSequentialDataBlock(1, list(range(1000, 1100)))
    context = ModbusServerContext(devices={5: ModbusDeviceContext(hr=hr)}, single=False)
    print("starting", flush=True)
    StartSerialServer(context, port=sys.argv[1], baudrate=19200, bytesize=8,
                      parity="N", stopbits=1, timeout=0.05)
    """
)


@pytest.fixture
def pymodbus_bus() -> Iterator[VirtualBus]:
    pytest.importorskip("pymodbus")
    with VirtualBus(3, baudrate=19200, parity="N") as bus:
        server = subprocess.Popen(
            [sys.executable, "-c", PYMODBUS_SERVER, bus.paths[0]],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env(),
        )
        try:
            assert server.stdout is not None
            assert server.stdout.readline().strip() == "starting"
            if not bus.wait_clients(0, timeout=10):
                server.kill()
                pytest.fail(f"pymodbus server did not open its port: {server.communicate()}")
            time.sleep(0.1)  # let the server's transport settle
            yield bus
        finally:
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(5)
            except subprocess.TimeoutExpired:
                server.kill()
                server.wait()


def test_minimalmodbus_client_reads_pymodbus_server(pymodbus_bus: VirtualBus) -> None:
    minimalmodbus = pytest.importorskip("minimalmodbus")
    instrument = minimalmodbus.Instrument(pymodbus_bus.paths[1], 5)
    instrument.serial.baudrate = 19200
    instrument.serial.timeout = 1.0
    try:
        assert instrument.read_registers(10, 4) == [1010, 1011, 1012, 1013]
        assert instrument.read_register(3) == 1003
    finally:
        instrument.serial.close()
    counters = pymodbus_bus.counters()
    assert counters.collisions == 0
    assert counters.drops[1].tx_bytes == 16  # two 8-byte requests


def test_pymodbus_client_reads_pymodbus_server(pymodbus_bus: VirtualBus) -> None:
    from pymodbus.client import ModbusSerialClient

    client = ModbusSerialClient(
        pymodbus_bus.paths[2], baudrate=19200, parity="N", timeout=1.0, retries=1
    )
    assert client.connect()
    try:
        rr = client.read_holding_registers(20, count=3, device_id=5)
        assert not rr.isError()
        assert rr.registers == [1020, 1021, 1022]
    finally:
        client.close()


def test_cli_vbus_standalone(tmp_path: Path) -> None:
    serial = pytest.importorskip("serial")
    cap = tmp_path / "cli.cap"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "pyrtu",
            "vbus",
            "--drops",
            "2",
            "--baud",
            "38400",
            "--dir",
            str(tmp_path / "bus"),
            "--capture",
            str(cap),
            "--echo",
            "1",
            "--stats",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env(),
    )
    try:
        assert proc.stdout is not None
        paths = [proc.stdout.readline().strip() for _ in range(2)]
        if "" in paths:
            proc.kill()
            pytest.fail(f"pyrtu vbus did not start: {proc.communicate()}")
        assert paths == [str(tmp_path / "bus" / "drop0"), str(tmp_path / "bus" / "drop1")]
        with (
            serial.Serial(paths[0], 38400, timeout=1) as a,
            serial.Serial(paths[1], 38400, timeout=1) as b,
        ):
            time.sleep(0.05)  # the hub notices the clients
            a.write(b"over the CLI bus")
            assert b.read(16) == b"over the CLI bus"
            b.write(b"echo")
            assert b.read(4) == b"echo"  # --echo 1
            assert a.read(4) == b"echo"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0
    assert "wire_bytes=20" in err
    assert not (tmp_path / "bus" / "drop0").exists()  # cleaned up
    assert load_capture(str(cap)).data == b"over the CLI busecho"


def test_cli_duration_and_main_in_process(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pyrtu.cli import COMMANDS, main

    assert "vbus" in COMMANDS
    assert main(["vbus", "--drops", "3", "--dir", str(tmp_path), "--duration", "0.1"]) == 0
    out = capsys.readouterr().out.split()
    assert out == [str(tmp_path / f"drop{i}") for i in range(3)]
    assert main([]) == 2
