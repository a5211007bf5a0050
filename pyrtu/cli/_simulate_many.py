"""``pyrtu simulate``'s drives: served, watched, and reopened when a port comes back.

``--port A --port B ...``: one simulated drive per port, all served by
`pyrtu.drivers.aio.AsyncSlave` on one event loop, in one thread of this process
(`DriveLoop`).  Many buses (the drops of several ``pyrtu vbus``) then cost one
process and one interpreter instead of one per drive.  A single ``--port`` is served
by the blocking `pyrtu.Slave` in its own thread (`DriveThread`: ``select()`` timing
to the microsecond).

`PortKeeper` keeps every port served: a port that fails (a USB adapter pulled, a
virtual-bus drop unplugged) is reported once, retried on the shared schedule of
`pyrtu.drivers.reconnect` (`Reconnect`, waits growing from 0.5 s to 30 s) and served again
by a new slave over the same simulator (the drive's state is kept) when it opens;
the other drives carry on meanwhile.  Time is an input of `PortKeeper.step`; the
command's main thread calls it between its waits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from pyrtu.drivers._loopthread import LoopThread
from pyrtu.drivers.reconnect import Backoff, Outage, Reconnect

__all__ = ["DriveLoop", "DriveThread", "PortKeeper", "PortReport"]


class Drives(Protocol):
    """What `PortKeeper` needs of the drives' driver (one slave per port)."""

    def error(self, index: int) -> BaseException | None:
        """The error that ended the slave of port ``index`` (None: it serves)."""
        ...

    def reopen(self, index: int) -> None:
        """Open port ``index`` again and serve it (raises when it cannot be opened)."""
        ...


def add_counters(total: dict[str, int], more: dict[str, int]) -> None:
    for key, value in more.items():
        total[key] = total.get(key, 0) + value


class DriveLoop:
    """Serve the slaves ``open_slave(i)`` makes (AsyncSlaves, not started), one per
    port, on a `LoopThread` until `stop`."""

    def __init__(self, open_slave: Callable[[int], Any], ports: int) -> None:
        self._open = open_slave
        self.slaves: list[Any] = []
        try:
            for i in range(ports):
                self.slaves.append(open_slave(i))
        except BaseException:
            for slave in self.slaves:
                slave.port.close()
            raise
        self._past: dict[str, int] = {}  # counters of the slaves of failed ports
        self._thread = LoopThread("pyrtu-simulate", self._begin, self._end)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Stop every slave and close its port; returns when the thread has ended."""
        self._thread.stop()

    @property
    def failure(self) -> BaseException | None:
        """What ended the drives' event loop while it served (None: it serves)."""
        return self._thread.died

    def error(self, index: int) -> BaseException | None:
        return self.slaves[index].error  # type: ignore[no-any-return]

    def reopen(self, index: int) -> None:
        slave = self._open(index)  # opens the port (raises PortError while it is away)
        try:
            self._thread.call(self._restart(index, slave), timeout=30)
        except BaseException:
            slave.port.close()
            raise

    async def _restart(self, index: int, slave: Any) -> None:
        old, self.slaves[index] = self.slaves[index], slave
        await old.close()  # its port closed when it failed: nothing is left on the loop
        add_counters(self._past, old.counters)
        slave.start()

    @property
    def counters(self) -> dict[str, int]:
        """The slaves' counters, added up (those of reopened ports included)."""
        total = dict(self._past)
        for slave in self.slaves:
            add_counters(total, slave.counters)
        return total

    async def _begin(self) -> None:
        for slave in self.slaves:
            slave.start()

    async def _end(self) -> None:
        for slave in self.slaves:
            try:
                await slave.close()
            except Exception:  # a failed port: already closed; the others still are
                continue


class DriveThread:
    """One port served by the blocking `pyrtu.Slave` ``open_slave()`` returns
    (started: the simulator's ``serve``)."""

    def __init__(self, open_slave: Callable[[], Any]) -> None:
        self._open = open_slave
        self.slave = open_slave()
        self._past: dict[str, int] = {}

    def error(self, index: int) -> BaseException | None:
        return self.slave.error  # type: ignore[no-any-return]

    def reopen(self, index: int) -> None:
        slave = self._open()
        old, self.slave = self.slave, slave
        add_counters(self._past, old.counters)
        old.close()

    @property
    def counters(self) -> dict[str, int]:
        total = dict(self._past)
        add_counters(total, self.slave.counters)
        return total


@dataclass(frozen=True)
class PortReport:
    """What `PortKeeper.step` has to say: a port ``lost`` (once per outage) or
    ``back`` (with the `Outage` that ended)."""

    kind: str  # "lost" or "back"
    port: str
    error: str
    outage: Outage | None = None


class PortKeeper:
    """The retry state of each port (`Reconnect`), driven by `step`."""

    def __init__(self, drives: Drives, ports: Sequence[str], backoff: Backoff | None = None):
        self.drives = drives
        self.ports = list(ports)
        self.retry = [Reconnect(backoff) for _ in self.ports]

    def step(self, now: float) -> list[PortReport]:
        """Notice failed ports, try to reopen those whose retry is due."""
        out: list[PortReport] = []
        for i, port in enumerate(self.ports):
            retry = self.retry[i]
            if not retry.down:
                exc = self.drives.error(i)
                if exc is not None and retry.failed(now, exc):
                    out.append(PortReport("lost", port, retry.outage.error if retry.outage else ""))
                continue
            if not retry.due(now):
                continue
            try:
                self.drives.reopen(i)
            except Exception as exc:  # PortError, termios.error...: still away
                retry.failed(now, exc)  # the same outage: not reported again
                continue
            outage = retry.recovered(now)
            out.append(PortReport("back", port, outage.error if outage else "", outage))
        return out

    def wait(self, now: float) -> float | None:
        """Seconds until the next retry is due (None: every port is up)."""
        waits = [r.wait(now) for r in self.retry if r.down]
        return min(waits) if waits else None

    def down(self) -> list[tuple[str, Outage]]:
        """The ports still down, with their outage."""
        return [
            (p, r.outage)
            for p, r in zip(self.ports, self.retry, strict=True)
            if r.outage is not None
        ]
