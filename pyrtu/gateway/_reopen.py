"""A bus the gateway can bring back after its port failed: `ReopeningBus`."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from pyrtu.pdu.errors import PortError

log = logging.getLogger("pyrtu.gateway")

Opener = Callable[[], Awaitable[Any]]


async def close_bus(bus: Any) -> None:
    """Close a bus object whose ``close`` may be sync or async."""
    result = bus.close()
    if asyncio.iscoroutine(result):
        await result


class ReopeningBus:
    """A bus made by ``opener`` (an async function returning a fresh
    `pyrtu.drivers.aio.AsyncMaster` or `pyrtu.tcp.AsyncTcpClient`), made again by
    `reopen` when its port failed: the gateway calls `reopen` on its back-off
    schedule (`pyrtu.drivers.reconnect`) until it works.  ``name`` names the port in the
    gateway's log lines.  One not opened yet is opened by `Gateway.start`: a port
    that is not there then (a USB adapter that appears after the gateway started)
    is a port that failed, retried on the same schedule."""

    def __init__(self, name: str, opener: Opener) -> None:
        self.name = name
        self._opener = opener
        self._bus: Any = None

    @property
    def is_open(self) -> bool:
        """Whether the bus is open (made by ``opener`` and not closed since)."""
        return self._bus is not None

    async def open(self) -> ReopeningBus:
        """Open the first time (`PortError` when the port is not there)."""
        self._bus = await self._opener()
        return self

    async def request(self, slave: int, pdu: bytes) -> bytes | None:
        bus = self._bus
        if bus is None:
            raise PortError(self.name, "the port is closed")
        result: bytes | None = await bus.request(slave, pdu)
        return result

    async def exchange(self, slave: int, pdu: bytes) -> bytes | None:
        """As the bus's ``exchange``: an exception answer as its PDU (what the gateway
        calls)."""
        bus = self._bus
        if bus is None:
            raise PortError(self.name, "the port is closed")
        result: bytes | None = await getattr(bus, "exchange", bus.request)(slave, pdu)
        return result

    async def reopen(self) -> None:
        """Close what is left of the failed port and open it again."""
        await self.close()
        self._bus = await self._opener()

    async def close(self) -> None:
        bus, self._bus = self._bus, None
        if bus is not None:
            try:
                await close_bus(bus)
            except Exception as exc:  # a port that is gone may fail to close: it is gone
                log.debug("%s: closing the failed port: %s", self.name, exc)

    def __repr__(self) -> str:
        return f"ReopeningBus({self.name!r})"
