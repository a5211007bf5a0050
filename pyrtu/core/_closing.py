"""The context-manager half of the drivers that own a port or a socket: ``with``
(or ``async with``) returns the object itself and calls its ``close`` on the way out,
whatever ended the block.  `Closing` for the sync drivers (`pyrtu.Slave`,
`pyrtu.tcp.TcpClient`), `AsyncClosing` for the asyncio ones (`pyrtu.drivers.aio.AsyncSlave`,
`pyrtu.tcp.AsyncTcpClient`, `pyrtu.tcp.server.TcpServer`).  `AsyncService` for the
asyncio services that ``start`` and ``stop`` (`pyrtu.poller.Poller`, `pyrtu.bridge.Bridge`):
``async with`` starts them and stops them on the way out."""

from __future__ import annotations

from typing import TypeVar

_C = TypeVar("_C", bound="Closing")
_A = TypeVar("_A", bound="AsyncClosing")
_S = TypeVar("_S", bound="AsyncService")


class Closing:
    """``with obj:`` closes ``obj`` at the end of the block."""

    def close(self) -> None:
        """Release what the object holds (each driver defines it)."""
        raise NotImplementedError

    def __enter__(self: _C) -> _C:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncClosing:
    """``async with obj:`` closes ``obj`` (awaited) at the end of the block."""

    async def close(self) -> None:
        """Release what the object holds (each driver defines it)."""
        raise NotImplementedError

    async def __aenter__(self: _A) -> _A:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class AsyncService:
    """``async with obj:`` awaits ``obj.start()``, and ``obj.stop()`` at the end of
    the block, whatever ended it."""

    async def start(self) -> None:
        """Start the service (each one defines it)."""
        raise NotImplementedError

    async def stop(self) -> None:
        """Stop the service and release what it holds (each one defines it)."""
        raise NotImplementedError

    async def __aenter__(self: _S) -> _S:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()


__all__ = ["AsyncClosing", "AsyncService", "Closing"]
