"""The interop peers against each other, without pyrtu's master or slave.

When a pyrtu-vs-peer test fails, these say whether the peer itself works on the
same path: the libmodbus client and server, pymodbus and minimalmodbus, over the
virtual bus (with wire timing) and over a socat pseudo-terminal pair.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from peers import pattern
from peers.tools import (
    PeerBinaries,
    libmodbus_bench,
    libmodbus_script,
    libmodbus_server,
    minimal_instrument,
    pymodbus_client,
    pymodbus_server,
)

from pyrtu.vbus import VirtualBus

pytest_plugins = ["peers.fixtures"]

BAUD = 115200


@pytest.fixture
def bus() -> Iterator[VirtualBus]:
    """Three drops: 0 client, 1 and 2 servers; 8N1 wire timing at 115200 baud."""
    with VirtualBus(3, baudrate=BAUD, parity="N") as b:
        yield b


def test_libmodbus_client_libmodbus_server_vbus(
    peer_binaries: PeerBinaries, bus: VirtualBus
) -> None:
    with libmodbus_server(peer_binaries, bus.paths[1], 5) as server:
        assert bus.wait_clients(1)
        report = libmodbus_bench(peer_binaries, bus.paths[0], 5, 300, address=40)
        assert report["errors"] == 0 and report["wrong"] == 0, report
        # the wire is the limit: 8 + 25 characters of 10 bits per transaction
        assert report["tps"] < 1.02 / (33 * bus.char_time)
    assert "replies=" in server.stats


def test_libmodbus_client_libmodbus_server_socat(
    peer_binaries: PeerBinaries, pty_pair: tuple[str, str]
) -> None:
    a, b = pty_pair
    with libmodbus_server(peer_binaries, b, 5):
        report = libmodbus_bench(peer_binaries, a, 5, 2000)
    assert report["errors"] == 0 and report["wrong"] == 0, report
    assert report["tps"] > 1000  # no wire: thousands per second


def test_libmodbus_script_against_libmodbus_server(
    peer_binaries: PeerBinaries, bus: VirtualBus
) -> None:
    s = 9
    ops = [
        "r01:3:10",
        "r02:7:9",
        "r03:100:5",
        "r04:998:2",
        "w06:5:1234",
        "r03:5:1",
        "w16:10:1,2,3",
        "m22:10:0xff00:0x0011",
        "rw23:10:2:20:7,8",
        "r03:20:2",
        "w05:3:1",
        "w15:0:1,1,0",
        "r01:0:4",
        "r03:999:2",  # crosses the end of the table
        "id17",
    ]
    with libmodbus_server(peer_binaries, bus.paths[1], s):
        assert bus.wait_clients(1)
        r = libmodbus_script(peer_binaries, bus.paths[0], s, ops)
    assert r[0]["values"] == pattern.coils(s, 3, 10)
    assert r[1]["values"] == pattern.discretes(s, 7, 9)
    assert r[2]["values"] == pattern.holdings(s, 100, 5)
    assert r[3]["values"] == pattern.inputs(s, 998, 2)
    assert r[5]["values"] == [1234]
    assert r[8]["values"] == [(1 & 0xFF00) | 0x0011, 2]  # FC 23 writes first
    assert r[9]["values"] == [7, 8]
    assert r[12]["values"] == [True, True, False, True]
    assert r[13] == {"op": "r03:999:2", "ok": False, "exception": 2}
    # libmodbus answers FC 17 with id 180 (its constant), run indicator ON, "LMB<version>"
    assert bytes.fromhex(r[14]["pdu"])[:5] == b"\xb4\xffLMB"


def test_pymodbus_client_libmodbus_server(peer_binaries: PeerBinaries, bus: VirtualBus) -> None:
    s = 17
    with libmodbus_server(peer_binaries, bus.paths[1], s):
        assert bus.wait_clients(1)
        client = pymodbus_client(bus.paths[0], baudrate=BAUD)
        try:
            for address in range(0, 200, 10):
                rr = client.read_holding_registers(address, count=10, device_id=s)
                assert not rr.isError(), rr
                assert rr.registers == pattern.holdings(s, address, 10)
            rr = client.read_input_registers(990, count=10, device_id=s)
            assert rr.registers == pattern.inputs(s, 990, 10)
            rr = client.read_coils(1, count=19, device_id=s)
            assert rr.bits[:19] == pattern.coils(s, 1, 19)
            assert not client.write_registers(50, [1, 2, 3], device_id=s).isError()
            assert client.read_holding_registers(50, count=3, device_id=s).registers == [1, 2, 3]
            rr = client.read_holding_registers(1000, count=1, device_id=s)
            assert rr.isError() and rr.exception_code == 2
        finally:
            client.close()


def test_pymodbus_client_libmodbus_server_socat(
    peer_binaries: PeerBinaries, pty_pair: tuple[str, str]
) -> None:
    a, b = pty_pair
    with libmodbus_server(peer_binaries, b, 3):
        client = pymodbus_client(a)
        try:
            for _ in range(50):
                assert client.read_holding_registers(0, count=10, device_id=3).registers == (
                    pattern.holdings(3, 0, 10)
                )
        finally:
            client.close()


def test_minimalmodbus_libmodbus_server(peer_binaries: PeerBinaries, bus: VirtualBus) -> None:
    s = 4
    with libmodbus_server(peer_binaries, bus.paths[1], s):
        assert bus.wait_clients(1)
        inst = minimal_instrument(bus.paths[0], s, baudrate=BAUD)
        try:
            assert inst.read_registers(20, 10) == pattern.holdings(s, 20, 10)
            assert inst.read_registers(7, 3, functioncode=4) == pattern.inputs(s, 7, 3)
            assert inst.read_bits(5, 12, functioncode=2) == [
                int(b) for b in pattern.discretes(s, 5, 12)
            ]
            inst.write_register(30, 4321)
            assert inst.read_register(30) == 4321
        finally:
            inst.serial.close()


def test_libmodbus_client_pymodbus_server(peer_binaries: PeerBinaries, bus: VirtualBus) -> None:
    """Validates the pymodbus peer: the pattern, writes, exception 2, and id 17."""
    s = 6
    with pymodbus_server(bus.paths[1], s):
        assert bus.wait_clients(1)
        r = libmodbus_script(
            peer_binaries,
            bus.paths[0],
            s,
            [
                "r01:3:10",
                "r02:7:9",
                "r03:100:5",
                "r04:998:2",
                "w16:10:1,2,3",
                "r03:10:3",
                "r03:999:2",
            ],
        )
        assert r[0]["values"] == pattern.coils(s, 3, 10)
        assert r[1]["values"] == pattern.discretes(s, 7, 9)
        assert r[2]["values"] == pattern.holdings(s, 100, 5)
        assert r[3]["values"] == pattern.inputs(s, 998, 2)
        assert r[5]["values"] == [1, 2, 3]
        assert r[6] == {"op": "r03:999:2", "ok": False, "exception": 2}
        report = libmodbus_bench(peer_binaries, bus.paths[0], s, 200, address=300)
        assert report["errors"] == 0 and report["wrong"] == 0, report


def test_peers_stay_silent_for_other_addresses(
    peer_binaries: PeerBinaries, bus: VirtualBus
) -> None:
    """Shared-bus manners of the server peers: no answer to another slave's request."""
    with pymodbus_server(bus.paths[1], 21), libmodbus_server(peer_binaries, bus.paths[2], 22):
        assert bus.wait_clients(1) and bus.wait_clients(2)
        r = libmodbus_script(peer_binaries, bus.paths[0], 23, ["r03:0:1"], timeout_ms=300)
        assert r[0]["ok"] is False and r[0]["errno"] != 0 and "exception" not in r[0]
        r = libmodbus_script(
            peer_binaries, bus.paths[0], 21, ["r03:0:2", "slave:22", "r03:0:2"], timeout_ms=300
        )
        assert r[0]["values"] == pattern.holdings(21, 0, 2)
        assert r[2]["values"] == pattern.holdings(22, 0, 2)
