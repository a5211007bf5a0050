"""RTU over TCP (``rtu+tcp://``): RTU frames, CRC kept, on a TCP socket, as serial
device servers carry them.  The device server here is socat joining a TCP listener
on 127.0.0.1 to a pseudo-terminal, with a real slave (pyrtu, libmodbus) on the pty."""

from __future__ import annotations

import asyncio
import re
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from peers import pattern
from peers.tools import (
    PeerBinaries,
    free_tcp_port,
    libmodbus_server,
    pyrtu_slave_process,
    socat_pty_over_tcp,
)

from pyrtu import AsyncMaster, ExceptionResponseError, Master, PortError
from pyrtu.tcp import rtu_over_tcp

pytest_plugins = ["peers.fixtures"]


@pytest.fixture
def device_server(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """(pty path, rtu+tcp URL): socat opens the pty, then listens on TCP."""
    link = tmp_path / "serial"
    with socat_pty_over_tcp(link) as port:
        yield str(link), f"rtu+tcp://127.0.0.1:{port}"


@pytest.mark.parametrize("peer", ["pyrtu", "libmodbus"])
def test_master_over_rtu_tcp(
    device_server: tuple[str, str], peer: str, peer_binaries: PeerBinaries
) -> None:
    path, url = device_server
    slave = (
        pyrtu_slave_process(path, 3, t35=0)
        if peer == "pyrtu"
        else libmodbus_server(peer_binaries, path, 3)
    )
    with slave, Master(rtu_over_tcp(url), t35=0, timeout=1.0) as m:
        assert m.read_holding_registers(3, 10, 5) == pattern.holdings(3, 10, 5)
        m.write_registers(3, 50, [11, 12])
        assert m.read_holding_registers(3, 50, 2) == [11, 12]
        assert m.read_coils(3, 0, 12) == pattern.coils(3, 0, 12)
        with pytest.raises(ExceptionResponseError):
            m.read_holding_registers(3, 60000, 2)
        assert m.counters["crc_errors"] == 0


def test_closing_the_master_closes_its_connection() -> None:
    """A master made from an ``rtu+tcp://`` URL owns the connection it made: its
    close (and the end of its ``with``) ends it at once, for `Master` and for
    `AsyncMaster` (the peer reads the end of the stream, no collection awaited)."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        url = f"rtu+tcp://127.0.0.1:{listener.getsockname()[1]}"
        listener.settimeout(5)
        masters: list[object] = []  # referenced after: the close ends it, not a collection
        with Master(url, t35=0, timeout=0.5) as m:
            masters.append(m)
            peer, _ = listener.accept()
        with peer:
            peer.settimeout(5)
            assert peer.recv(16) == b""

        async def with_async() -> None:
            async with AsyncMaster(url, t35=0, timeout=0.5) as am:
                masters.append(am)

        asyncio.run(with_async())
        peer, _ = listener.accept()
        with peer:
            peer.settimeout(5)
            assert peer.recv(16) == b""
        assert len(masters) == 2


def test_bad_urls_and_refused_connections() -> None:
    with pytest.raises(ValueError, match="rtu\\+tcp://"):
        rtu_over_tcp("tcp://127.0.0.1:1")
    with pytest.raises(PortError, match="cannot connect"):
        rtu_over_tcp(f"rtu+tcp://127.0.0.1:{free_tcp_port()}")


def test_a_device_server_that_goes_away_is_said_once(tmp_path: Path) -> None:
    """The device server closes the connection: the request fails with a `PortError`
    saying "read failed" (or "write failed") once, with pyserial's reason, not
    "read failed: read failed: socket disconnected"."""
    link = tmp_path / "serial"
    with socat_pty_over_tcp(link) as port:
        url = f"rtu+tcp://127.0.0.1:{port}"
        with pyrtu_slave_process(str(link), 3, t35=0):
            m = Master(url, t35=0, timeout=1.0)
            assert m.read_holding_registers(3, 10, 2) == pattern.holdings(3, 10, 2)
    try:
        with pytest.raises(PortError) as info:
            m.read_holding_registers(3, 10, 2)
        text = str(info.value)
        assert text.startswith(f"socket://127.0.0.1:{port}: "), text
        reason = text.removeprefix(f"socket://127.0.0.1:{port}: ")
        assert re.match(r"(read|write) failed: ", reason), text
        assert reason.count("failed: ") == 1, text
    finally:
        m.close()
