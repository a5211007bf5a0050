"""The masters a `Poller` drives: anything with `pyrtu.Master`'s method names as
coroutines (`pyrtu.aio.AsyncMaster`'s API), ``last_answer_time`` and ``close()``.

The default is `pyrtu.aio.AsyncMaster` (``loop.add_reader`` on the port, one
wake-up per answer; ports without a descriptor are read in a thread of its own).
`ThreadMaster` runs a sync `pyrtu.Master` on a worker thread of its own per bus:
the fallback (``Poller(master="thread")``) for ports or drivers only the sync
master handles.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import functools
from collections.abc import Callable, Sequence
from typing import Any, Protocol, TypeVar

from ..aio import AsyncMaster
from ..errors import ModbusError, PortError
from ..master import Master
from .config import Bus

T = TypeVar("T")

#: read and write function codes -> the master's method names
METHODS = {1: "read_coils", 2: "read_discrete_inputs", 3: "read_holding_registers",
           4: "read_input_registers", 5: "write_coil", 6: "write_register",
           15: "write_coils", 16: "write_registers"}  # fmt: skip


class AsyncMasterLike(Protocol):
    """What a poller needs of a master (`pyrtu.aio.AsyncMaster` has it)."""

    @property
    def last_answer_time(self) -> float | None: ...

    async def read_coils(self, slave: int, address: int, count: int) -> list[bool]: ...

    async def read_discrete_inputs(self, slave: int, address: int, count: int) -> list[bool]: ...

    async def read_holding_registers(self, slave: int, address: int, count: int) -> list[int]: ...

    async def read_input_registers(self, slave: int, address: int, count: int) -> list[int]: ...

    async def write_coil(self, slave: int, address: int, value: bool) -> None: ...

    async def write_register(self, slave: int, address: int, value: int) -> None: ...

    async def write_coils(self, slave: int, address: int, values: Sequence[bool]) -> None: ...

    async def write_registers(self, slave: int, address: int, values: Sequence[int]) -> None: ...

    async def close(self) -> None: ...


class ThreadMaster:
    """A sync `pyrtu.Master` behind coroutines, on one worker thread."""

    def __init__(self, master: Master) -> None:
        self.master = master
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="pyrtu-poll")
        self.last_answer_time: float | None = None

    @classmethod
    def open(cls, bus: Bus) -> ThreadMaster:
        """A `pyrtu.Master` on the bus's port with its keywords (PortError if the port
        cannot be opened)."""
        return cls(Master(bus.port, **dict(bus.master)))

    async def _run(self, fn: Callable[..., T], *args: Any) -> T:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._pool, functools.partial(self._call, fn, *args))

    def _call(self, fn: Callable[..., T], *args: Any) -> T:
        try:
            return fn(*args)
        finally:
            self.last_answer_time = self.master.last_answer_time

    async def read_coils(self, slave: int, address: int, count: int) -> list[bool]:
        return await self._run(self.master.read_coils, slave, address, count)

    async def read_discrete_inputs(self, slave: int, address: int, count: int) -> list[bool]:
        return await self._run(self.master.read_discrete_inputs, slave, address, count)

    async def read_holding_registers(self, slave: int, address: int, count: int) -> list[int]:
        return await self._run(self.master.read_holding_registers, slave, address, count)

    async def read_input_registers(self, slave: int, address: int, count: int) -> list[int]:
        return await self._run(self.master.read_input_registers, slave, address, count)

    async def write_coil(self, slave: int, address: int, value: bool) -> None:
        await self._run(self.master.write_coil, slave, address, value)

    async def write_register(self, slave: int, address: int, value: int) -> None:
        await self._run(self.master.write_register, slave, address, value)

    async def write_coils(self, slave: int, address: int, values: Sequence[bool]) -> None:
        await self._run(self.master.write_coils, slave, address, values)

    async def write_registers(self, slave: int, address: int, values: Sequence[int]) -> None:
        await self._run(self.master.write_registers, slave, address, values)

    @property
    def counters(self) -> dict[str, int]:
        return self.master.counters

    async def close(self) -> None:
        try:
            await self._run(self.master.close)
        finally:
            self._pool.shutdown(wait=False)


def open_thread_master(bus: Bus) -> AsyncMasterLike:
    """A `ThreadMaster` for ``bus``."""
    return ThreadMaster.open(bus)


def open_async_master(bus: Bus) -> AsyncMasterLike:
    """A `pyrtu.aio.AsyncMaster` on the bus's port with its keywords (call it in the
    event loop's thread)."""
    return AsyncMaster(bus.port, **dict(bus.master))


#: the masters `Poller(master=...)` names
FACTORIES = {"aio": open_async_master, "thread": open_thread_master}


async def open_master(factory: Callable[[Bus], AsyncMasterLike], bus: Bus) -> AsyncMasterLike:
    """``factory(bus)``; the sync master's open (a blocking TCP connect) runs on a
    worker thread, so a port that is slow to refuse holds up no other bus."""
    if factory is open_thread_master:
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(None, open_thread_master, bus)
    return factory(bus)


def is_port_error(exc: BaseException) -> bool:
    """Whether a master's error means its port failed (`PortError`, an OS error of
    the device or the connection), not its slave (no answer, a bad answer, an
    exception response: `ModbusError`s; timeouts)."""
    if isinstance(exc, PortError):
        return True
    return isinstance(exc, OSError) and not isinstance(exc, ModbusError | TimeoutError)


__all__ = [
    "FACTORIES",
    "METHODS",
    "AsyncMasterLike",
    "ThreadMaster",
    "is_port_error",
    "open_async_master",
    "open_master",
    "open_thread_master",
]
