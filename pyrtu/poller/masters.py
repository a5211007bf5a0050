"""The masters a `Poller` drives: anything with `pyrtu.drivers.aio.AsyncMaster`'s
``transact`` (a request of the masters' one table in, ``(value, end_time)`` out)
and ``close()``.

The default is `pyrtu.drivers.aio.AsyncMaster` (``loop.add_reader`` on the port, one
wake-up per answer; ports without a descriptor are read in a thread of its own).
`ThreadMaster` runs a sync `pyrtu.Master` on a worker thread of its own per bus:
the fallback (``Poller(master="thread")``) for ports or drivers only the sync
master handles.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
from collections.abc import Callable
from typing import Any, Protocol

from pyrtu.drivers._portname import url_scheme
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.links import transport_of
from pyrtu.drivers.master import Master
from pyrtu.pdu import requests as request_table
from pyrtu.pdu.errors import ModbusError, PortBusyError, PortError
from pyrtu.pdu.requests import Request

from .config import Bus
from .connect import NETWORK_SCHEMES

#: the requests the poller sends, by function code (the masters' one table)
BY_FUNCTION: dict[int, Request[Any]] = request_table.BY_FUNCTION


class AsyncMasterLike(Protocol):
    """What a poller needs of a master (`pyrtu.drivers.aio.AsyncMaster` has it): one request
    of the table (`pyrtu.pdu.requests.Request`) with its arguments in, ``(value,
    end_time)`` out, ``end_time`` being when the answer's last byte came."""

    async def transact(self, req: Request[Any], slave: int, *args: Any) -> tuple[Any, float]: ...

    async def close(self) -> None: ...


class ThreadMaster:
    """A sync `pyrtu.Master` behind coroutines, on one worker thread."""

    def __init__(self, master: Master) -> None:
        self.master = master
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pyrtu-poll")

    @classmethod
    def open(cls, bus: Bus) -> ThreadMaster:
        """A `pyrtu.Master` on the bus's port with its keywords (PortError if the port
        cannot be opened)."""
        return cls(Master(bus.port, line=bus.line, **bus.master_options))

    async def transact(self, req: Request[Any], slave: int, *args: Any) -> tuple[Any, float]:
        """`pyrtu.Master.transact` on the worker thread."""
        loop = asyncio.get_running_loop()
        call = functools.partial(self.master.transact, req, slave, *args)
        return await loop.run_in_executor(self._pool, call)

    @property
    def last_answer_time(self) -> float | None:
        return self.master.last_answer_time

    @property
    def counters(self) -> dict[str, int]:
        return self.master.counters

    async def close(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            await loop.run_in_executor(self._pool, self.master.close)
        finally:
            self._pool.shutdown(wait=False)


def open_thread_master(bus: Bus) -> AsyncMasterLike:
    """A `ThreadMaster` for ``bus``."""
    return ThreadMaster.open(bus)


def open_async_master(bus: Bus) -> AsyncMasterLike:
    """A `pyrtu.drivers.aio.AsyncMaster` on the bus's port with its keywords (call it in the
    event loop's thread)."""
    return AsyncMaster(bus.port, line=bus.line, **bus.master_options)


#: the masters `Poller(master=...)` names
FACTORIES = {"aio": open_async_master, "thread": open_thread_master}


def _blocking_open(factory: Callable[[Bus], AsyncMasterLike], bus: Bus) -> bool:
    """Whether ``factory(bus)`` may wait on the network: the sync master's open (a
    blocking TCP connect) and the asyncio master's on a network port other than an
    MBAP one (``tcp://``, ``mbaps://``, ``udp://``: `pyrtu.drivers.links.Transport.mbap`,
    whose asyncio link opens its socket at the first request): ``rtu+tcp://``,
    ``socket://`` (pyserial connects as it opens)."""
    if factory is open_thread_master:
        return True
    scheme = url_scheme(bus.port) if isinstance(bus.port, str) else None
    return (
        factory is open_async_master
        and scheme in NETWORK_SCHEMES
        and not transport_of(bus.port).mbap
    )


async def open_master(factory: Callable[[Bus], AsyncMasterLike], bus: Bus) -> AsyncMasterLike:
    """``factory(bus)``; an open that may wait on the network (`_blocking_open`)
    runs on a worker thread, so a port that is slow to refuse holds up no other
    bus.  A busy port's error gives no advice: the poller has no ``exclusive`` to
    pass."""
    try:
        if _blocking_open(factory, bus):
            loop = asyncio.get_running_loop()
            return await loop.run_in_executor(None, factory, bus)
        return factory(bus)
    except PortBusyError as exc:
        raise exc.with_advice(None) from exc.__cause__


def is_port_error(exc: BaseException) -> bool:
    """Whether a master's error means its port failed (`PortError`, an OS error of
    the device or the connection), not its slave (no answer, a bad answer, an
    exception response: `ModbusError`s; timeouts)."""
    if isinstance(exc, PortError):
        return True
    return isinstance(exc, OSError) and not isinstance(exc, ModbusError | TimeoutError)


__all__ = [
    "BY_FUNCTION",
    "FACTORIES",
    "AsyncMasterLike",
    "ThreadMaster",
    "is_port_error",
    "open_async_master",
    "open_master",
    "open_thread_master",
]
