"""TCP_NODELAY on every TCP socket pyrtu opens or accepts (issue 27.6): the MQTT
connection of the bridge, the Modbus TCP clients, ``rtu+tcp://``, and the
connections the TCP server and the gateway (Modbus TCP and RTU over TCP) accept.
Without it a small write that follows an unacknowledged one waits for the peer's
delayed ACK (40 ms on Linux): the bridge's set round trip took 44 ms, not 3.

Each socket is asked with getsockopt, on the real connection to a real peer."""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path
from typing import Any

from mqtt_broker import Broker

from pyrtu.gateway import Gateway
from pyrtu.tcp import AsyncTcpClient, TcpClient, rtu_over_tcp
from pyrtu.tcp.server import LocalBus, TcpServer

READ_1 = bytes([3, 0, 0, 0, 1])  # read one holding register from address 0


def nodelay(sock: Any) -> bool:
    return bool(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))


def accepted(gateway: Gateway) -> list[Any]:
    """The sockets of the connections a gateway accepted."""
    conns = gateway._connections.values()
    return [c.transport.get_extra_info("socket") for c in conns if c.transport is not None]


def test_the_bridge_mqtt_socket(tmp_path: Path) -> None:
    from pyrtu.bridge.config import MqttConfig
    from pyrtu.bridge.mqtt import MqttLink

    async def main(url: str) -> None:
        link = MqttLink(
            MqttConfig(url=url),
            "pyrtu/nodelay/status",
            on_message=lambda msg: None,
            on_ack=lambda mid: None,
            on_lost=lambda reason: None,
        )
        await link.connect(timeout=10)
        try:
            assert link.client is not None
            assert nodelay(link.client.socket())
        finally:
            link.close()

    with Broker(tmp_path) as broker:
        asyncio.run(main(broker.url))


def test_the_tcp_server_and_both_modbus_tcp_clients() -> None:
    async def main() -> None:
        async with TcpServer.for_store(1) as server:
            await server.start("127.0.0.1", 0)
            assert server.address is not None
            host, port = server.address
            url = f"tcp://{host}:{port}"
            async with await AsyncTcpClient.connect(url) as aclient:
                await aclient.request(1, READ_1, raw=True)
                assert nodelay(aclient._conn.transport.get_extra_info("socket"))
                with TcpClient(url) as client:
                    await asyncio.to_thread(lambda: client.request(1, READ_1, raw=True))
                    assert nodelay(client._sock)
                    served = accepted(server._gateway)
                    assert len(served) == 2
                    assert all(nodelay(s) for s in served)

    asyncio.run(main())


def test_the_gateway_modbus_tcp_and_rtu_over_tcp_listeners() -> None:
    from pyrtu.core.line import LineConfig
    from pyrtu.drivers.slave_base import SlaveBase

    async def main() -> None:
        slave = SlaveBase(1, line=LineConfig())
        gw = Gateway([(LocalBus(slave), {1: 1})])
        await gw.start("127.0.0.1", 0, rtu=("127.0.0.1", 0))
        try:
            assert gw.address is not None and gw.rtu_address is not None
            host, port = gw.address
            async with await AsyncTcpClient.connect(f"tcp://{host}:{port}") as client:
                await client.request(1, READ_1, raw=True)
                rhost, rport = gw.rtu_address
                link = rtu_over_tcp(f"rtu+tcp://{rhost}:{rport}")
                try:
                    assert nodelay(link._socket)  # the rtu+tcp:// client's socket
                    while len(accepted(gw)) < 2:  # the RTU listener's connection
                        await asyncio.sleep(0.01)
                    assert all(nodelay(s) for s in accepted(gw))
                finally:
                    link.close()
        finally:
            await gw.close()

    asyncio.run(main())
