"""The attributes and constructor checks that Slave, AsyncSlave, TcpClient and
AsyncTcpClient share (issue 18 moved them into one constructor, one mixin and
forwarding descriptors): each behaves as the explicit code did, on real ptys and a
real TCP server."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator

import pytest
from peers.tools import free_tcp_port, pymodbus_server
from ptylink import PtyLink, make_store

from pyrtu import pdu
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import AsyncSlave
from pyrtu.drivers.slave import Slave
from pyrtu.tcp import AsyncTcpClient, TcpClient


@pytest.fixture
def link() -> Iterator[PtyLink]:
    with PtyLink() as pty:
        yield pty


@pytest.mark.parametrize("cls", [Slave, AsyncSlave])
def test_slave_flags_forward_to_the_line_state(link: PtyLink, cls: type) -> None:
    slave = cls(link.path_b, address=1, store=make_store(), parity="N")
    try:
        assert slave.busy is False and slave.listen_only is False
        slave.busy = 1  # converted, as the setter did
        assert slave.busy is True and slave.line.busy is True
        slave.line.listen_only = True
        assert slave.listen_only is True
        with pytest.raises(AttributeError, match=r"'listen_only' of '\w*Slave' object has no"):
            slave.listen_only = False
        assert slave.line.listen_only is True  # nothing changed
        slave.busy = 0
        assert slave.line.busy is False
        assert slave.error is None
    finally:
        if isinstance(slave, AsyncSlave):
            asyncio.run(slave.close())
        else:
            slave.close()


@pytest.mark.parametrize("cls", [Slave, AsyncSlave])
def test_slave_constructor_errors_name_the_class(link: PtyLink, cls: type) -> None:
    name = cls.__name__
    with pytest.raises(
        TypeError, match=rf"^{name}\(\) got an unexpected keyword argument 'pairty'$"
    ):
        cls(link.path_b, pairty="N")
    with pytest.raises(TypeError, match=rf"^{name}: give line= or the line keywords \(parity\)"):
        cls(link.path_b, line=LineConfig(), parity="O")
    for delay in (-1, math.inf, math.nan):  # infinity: a slave that never answers
        with pytest.raises(ValueError, match="response_delay must be a non-negative"):
            cls(link.path_b, parity="N", response_delay=delay)
    with pytest.raises(ValueError, match=r"a slave address is 1\.\.247, not 0"):
        cls(link.path_b, address=0, parity="N")


def test_slave_keywords_reach_the_slave_and_the_port(link: PtyLink) -> None:
    seen: list[Slave] = []
    with Slave(
        link.path_b,
        address=[3, 4],
        store=make_store(),
        parity="N",
        stopbits=2,
        echo=True,
        functions=[3],
        server_id=b"x",
        run_indicator=False,
        response_delay=0.25,
        watchdog=2.0,
        on_watchdog=seen.append,
        exclusive=False,
    ) as slave:
        assert slave.addresses == frozenset({3, 4})
        assert slave.line_config.stopbits == 2 and slave.port.stopbits == 2
        assert slave.echo is True and slave.functions == {3}
        assert (slave.server_id, slave.run_indicator) == (b"x", False)
        assert (slave.response_delay, slave.watchdog) == (0.25, 2.0)
        slave.watchdog_expired()
        assert seen == [slave]
    assert slave.port.closed


def test_tcp_client_state_forwards_to_its_protocol() -> None:
    port = free_tcp_port()
    with pymodbus_server(f"127.0.0.1:{port}", 1, mode="tcp"):
        with TcpClient(f"tcp://127.0.0.1:{port}", timeout=2.0) as c:
            assert c.timeout == 2.0 and c.last_answer_time is None
            c.timeout = 1
            assert c.timeout == 1.0 and isinstance(c.timeout, float)
            with pytest.raises(ValueError, match="timeout must be a positive number of seconds"):
                c.timeout = 0
            assert c.timeout == 1.0
            with pytest.raises(AttributeError, match="'last_answer_time' of 'TcpClient'"):
                c.last_answer_time = 1.0
            assert c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 1)) is not None
            assert c.last_answer_time is not None
            assert c.counters["requests"] == 1
            c.counters["requests"] = 99  # a copy
            assert c.counters["requests"] == 1

        async def main() -> None:
            client = await AsyncTcpClient.connect(f"tcp://127.0.0.1:{port}", timeout=2.0)
            async with client as c:
                assert c.timeout == 2.0 and c.last_answer_time is None
                c.timeout = 0.5
                assert c.timeout == 0.5
                with pytest.raises(ValueError, match="timeout must be a positive"):
                    c.timeout = float("nan")
                await c.request(1, pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 1))
                assert c.last_answer_time is not None and c.counters["requests"] == 1

        asyncio.run(main())
