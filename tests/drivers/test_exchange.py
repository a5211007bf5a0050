"""An exception answer as its PDU, without an exception object: the masters'
``exchange`` (serial protocol, Modbus TCP) and the gateway that forwards what a
bus's ``exchange`` returns."""

from __future__ import annotations

import asyncio
from types import ModuleType

import pytest
from peers.tools import pyrtu_slave_process

from pyrtu import ExceptionResponseError, Master
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.gateway import Gateway
from pyrtu.pdu.requests import REQUESTS, exchange, read_holding_registers
from pyrtu.protocol.client import ClientProtocol, ClientState
from pyrtu.tcp import AsyncTcpClient

pytest_plugins = ["peers.fixtures"]

LINE = LineConfig(baudrate=9600, parity="N")
READ_BEYOND = b"\x03\xea\x60\x00\x05"  # FC 3 at 60000: exception 0x02 from the peers


def transact(p: ClientProtocol, call: tuple[int, bytes, object], answer: bytes) -> object:
    t = p.tx_end + 1.0
    p.start(*call, now=t)  # type: ignore[arg-type]
    p.handle_timer(t)
    p.wait_done(b"", t)
    p.transmitted(t + 0.01, t)
    p.receive_data(answer, t + 0.05)
    assert p.state is ClientState.DONE
    return p.result()


def test_exchange_returns_an_exception_answer_as_its_pdu(backend: ModuleType) -> None:
    p = ClientProtocol(LINE, timeout=0.5, backend=backend)
    exception = bytes(backend.add_crc(bytes.fromhex("018302")))
    assert transact(p, exchange(1, bytes.fromhex("030000000a")), exception) == b"\x83\x02"
    assert p.counters["exceptions"] == 1 and p.answer_end is not None
    answer = bytes(backend.add_crc(bytes.fromhex("0103020007")))
    assert transact(p, exchange(1, bytes.fromhex("0300000001")), answer) == b"\x03\x02\x00\x07"
    with pytest.raises(ExceptionResponseError) as info:  # the other requests still raise
        transact(p, read_holding_registers(1, 0, 10), exception)
    assert info.value.code == 2
    assert exchange(0, b"\x06\x00\x01\x00\x02").decode is None  # a broadcast: no answer
    with pytest.raises(ValueError, match="exchange: pdu is empty"):
        exchange(1, b"")
    assert "exchange" in REQUESTS


class ExchangeOnly:
    """A bus whose exception answers come from ``exchange`` only: ``request`` must not
    be called (it raises, as AsyncMaster's does for an exception answer)."""

    calls = 0

    async def request(self, slave: int, pdu: bytes) -> bytes | None:
        raise ExceptionResponseError(slave, pdu[0], 0x02)

    async def exchange(self, slave: int, pdu: bytes) -> bytes | None:
        self.calls += 1
        return bytes((pdu[0] | 0x80, 0x02))


def test_gateway_forwards_the_exception_answer_of_the_bus_exchange() -> None:
    async def main() -> None:
        bus = ExchangeOnly()
        gw = Gateway([(bus, range(1, 5))])
        await gw.start("127.0.0.1", 0)
        assert gw.address is not None
        c = await AsyncTcpClient.connect(f"tcp://{gw.address[0]}:{gw.address[1]}", timeout=5.0)
        assert await c.exchange(3, b"\x03\x00\x00\x00\x01") == b"\x83\x02"
        with pytest.raises(ExceptionResponseError) as info:
            await c.request(3, b"\x03\x00\x00\x00\x01")
        assert info.value.code == 0x02
        assert bus.calls == 2 and gw.counters["exceptions"] == 2
        await c.close()
        await gw.close()

    asyncio.run(main())


def test_masters_exchange_with_a_libmodbus_tcp_server(libmodbus_tcp: str) -> None:
    with Master(libmodbus_tcp, timeout=2.0) as m:
        assert m.exchange(1, READ_BEYOND) == b"\x83\x02"
        assert m.exchange(1, b"\x03\x00\x00\x00\x01")[:2] == b"\x03\x02"
        with pytest.raises(ExceptionResponseError):
            m.request(1, READ_BEYOND)

    async def main() -> None:
        async with AsyncMaster(libmodbus_tcp, timeout=2.0) as m:
            assert await m.exchange(1, READ_BEYOND) == b"\x83\x02"
        c = await AsyncTcpClient.connect(libmodbus_tcp, timeout=2.0)
        assert await c.exchange(1, READ_BEYOND) == b"\x83\x02"
        await c.close()

    asyncio.run(main())


def test_masters_exchange_on_a_serial_line(pty_pair: tuple[str, str]) -> None:
    """Master and AsyncMaster on a pty, a pyrtu slave process on the other end."""
    with pyrtu_slave_process(pty_pair[1], 4):
        with Master(pty_pair[0], baudrate=115200, parity="N", timeout=1.0) as m:
            assert m.exchange(4, READ_BEYOND) == b"\x83\x02"
            assert m.counters["exceptions"] == 1

        async def main() -> None:
            async with AsyncMaster(pty_pair[0], baudrate=115200, parity="N", timeout=1.0) as m:
                assert await m.exchange(4, READ_BEYOND) == b"\x83\x02"
                with pytest.raises(ExceptionResponseError):
                    await m.request(4, READ_BEYOND)

        asyncio.run(main())
