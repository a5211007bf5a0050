"""``pyrtu simulate``'s metrics: the drives' counters on their serial ports (the
slaves' own: requests, responses, exception responses, broadcasts, frames for
other addresses, the FC 08 diagnostic counters), each port's state, and with
``--tcp`` the TCP server's counters and connected clients (the gateway's
families, `pyrtu.metrics.gateway.counter_families`, read on the server's loop).

The serial counters are read from the HTTP server's thread: each slave hands out
a copy taken under its lock (`pyrtu.drivers.slave_base.SlaveBase.counters`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric

from pyrtu.drivers.reconnect import Outage
from pyrtu.drivers.supervise import cause

from .gateway import counter_families
from .server import on_loop

#: (slave counter, metric, help) of the serial side
SERIAL_COUNTERS = (
    ("requests", "pyrtu_simulate_requests", "Requests addressed to the drive (serial)"),
    ("responses", "pyrtu_simulate_responses", "Normal responses sent (serial)"),
    ("exceptions", "pyrtu_simulate_exceptions", "Exception responses sent (serial)"),
    ("broadcasts", "pyrtu_simulate_broadcasts", "Broadcasts received (serial)"),
    ("ignored", "pyrtu_simulate_ignored_frames", "Frames for other addresses (serial)"),
)
#: (slave counter, ``kind`` label) of ``pyrtu_simulate_errors_total``
SERIAL_ERRORS = (
    ("bus_communication_error_count", "frame"),
    ("bus_character_overrun_count", "overrun"),
    ("slave_no_response_count", "no_response"),
    ("watchdog_trips", "watchdog"),
)


class Watched(Protocol):
    """A thread of the command: ``failure`` is why it ended (None: it serves)."""

    @property
    def failure(self) -> BaseException | None: ...


class TcpStats(Protocol):
    """A `TcpServer`, or the servers of a ``--tcp`` range as one
    (`pyrtu.cli._simulate_tcp.ServerGroup`)."""

    def stats(self) -> dict[str, object]: ...

    def health(self) -> list[str]: ...


class TcpSide(Protocol):
    """``--tcp``'s server on its loop (`pyrtu.cli._simulate_tcp.TcpThread`)."""

    loop: asyncio.AbstractEventLoop

    @property
    def server(self) -> TcpStats: ...


class SimulateSource:
    """``pyrtu simulate``'s `pyrtu.metrics.server.Source`: ``counters`` the drives'
    serial counters added up (None: TCP only), ``ports`` and ``down`` (the ports
    and those down, with their outage), ``tcp`` the TCP server (None: none),
    ``watched`` the threads that serve, named."""

    def __init__(
        self,
        counters: Callable[[], dict[str, int]] | None,
        ports: Sequence[str],
        down: Callable[[], list[tuple[str, Outage]]],
        tcp: TcpSide | None,
        watched: Sequence[tuple[str, Watched]],
    ) -> None:
        self.counters = counters
        self.ports = list(ports)
        self.down = down
        self.tcp = tcp
        self.watched = list(watched)

    def collect(self) -> Iterator[Metric]:
        if self.counters is not None:
            counts = self.counters()
            for key, name, documentation in SERIAL_COUNTERS:
                counter = CounterMetricFamily(name, documentation)
                counter.add_metric([], counts.get(key, 0))
                yield counter
            errors = CounterMetricFamily(
                "pyrtu_simulate_errors",
                "Serial-line errors by kind (the FC 08 diagnostic counters, watchdog trips)",
                labels=["kind"],
            )
            for key, kind in SERIAL_ERRORS:
                errors.add_metric([kind], counts.get(key, 0))
            yield errors
        down = {port for port, _ in self.down()}
        up = GaugeMetricFamily(
            "pyrtu_simulate_port_up",
            "0 while the serial port is down (reopened when it is back), else 1",
            labels=["port"],
        )
        for port in self.ports:
            up.add_metric([port], 0 if port in down else 1)
        yield up
        tcp = self.tcp
        if tcp is not None:
            stats: dict[str, Any] = on_loop(tcp.loop, tcp.server.stats)
            yield from counter_families("pyrtu_simulate_tcp", stats)

    def health(self) -> list[str]:
        problems = []
        dead: set[int] = set()
        for what, thread in self.watched:
            failure = thread.failure
            if failure is not None:
                problems.append(f"{what} stopped: {cause(failure)}")
                dead.add(id(thread))
        for port, outage in self.down():
            problems.append(f"port {port} down: {outage.error.removeprefix(port + ': ')}")
        tcp = self.tcp
        if tcp is not None and id(tcp) not in dead:  # (a dead thread's loop answers no one)
            problems += on_loop(tcp.loop, tcp.server.health)
        return problems


__all__ = ["SimulateSource"]
