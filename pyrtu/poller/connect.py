"""How a poller with many network buses connects: bounded, per host, staggered.

A thousand ``tcp://`` buses must not all connect at the same instant (at start, or
again after a network blip): `ConnectLimits` says how many connects may be in
progress at once in the whole poller (``max_connecting``) and to one host
(``max_connecting_per_host``), how fast the network buses start
(``start_rate``: their first connects, and so the phase of their polls, spread
evenly, one bus every ``1 / start_rate`` seconds), how much the reconnect waits
of a network bus are spread (``jitter``, a fraction of `pyrtu.drivers.reconnect`'s
wait, for every network bus) and how late a network bus's poll may be for the
sake of a wake-up shared with others (``lateness``).  In TOML, a ``[connect]``
table with those keys; `ConnectGate` enforces the two bounds on the poller's
event loop.

A connect holds its slots only while the connection is being made (at most the
bus's timeout): a device that refuses gives them back at once, one that never
completes the handshake after its timeout, one that accepts and never answers at
once (its silence is its transactions' timeouts, on its own bus task).  So with
``max_connecting`` >= 2 one bad device delays no other's connect.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from dataclasses import dataclass, fields
from typing import Any
from urllib.parse import urlsplit

from pyrtu.drivers._portname import NETWORK_SCHEMES, url_scheme

#: defaults of the ``[connect]`` keys (docs/many-devices.md says why)
MAX_CONNECTING = 64
MAX_CONNECTING_PER_HOST = 8
START_RATE = 1000.0
JITTER = 0.5
LATENESS = 0.025


def _count(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: must be a positive integer, not {value!r}")
    return value


@dataclass(frozen=True)
class ConnectLimits:
    """The ``[connect]`` settings (see the module docstring); ValueError
    ``"key: what"`` for a value that cannot be used."""

    #: connects in progress at once, over all buses
    max_connecting: int = MAX_CONNECTING
    #: connects in progress at once to one host (a gateway, a device server)
    max_connecting_per_host: int = MAX_CONNECTING_PER_HOST
    #: network buses started per second (their first connects and polls spread)
    start_rate: float = START_RATE
    #: the reconnect wait of a network bus, spread by +- this fraction of it
    jitter: float = JITTER
    #: how late a network bus's poll may be, as a fraction of its shortest interval
    #: (and in seconds, for an interval over a second): its polls wake on a grid
    #: of that step, shared with the other buses (`pyrtu.poller.driver.wake_tick`)
    lateness: float = LATENESS

    def __post_init__(self) -> None:
        _count("max_connecting", self.max_connecting)
        _count("max_connecting_per_host", self.max_connecting_per_host)
        rate = self.start_rate
        if isinstance(rate, bool) or not isinstance(rate, int | float) or not rate > 0:
            raise ValueError(
                f"start_rate: must be a positive number of buses a second, not {rate!r}"
            )
        j = self.jitter
        if isinstance(j, bool) or not isinstance(j, int | float) or not 0 <= j < 1:
            raise ValueError(f"jitter: must be a fraction in [0, 1), not {j!r}")
        late = self.lateness
        if isinstance(late, bool) or not isinstance(late, int | float) or not 0 < late <= 0.5:
            raise ValueError(f"lateness: must be a fraction in (0, 0.5], not {late!r}")

    def start_offset(self, rank: int) -> float:
        """Seconds after the start at which the ``rank``-th network bus (0: the first)
        connects and polls first."""
        return 0.0 if math.isinf(self.start_rate) else rank / self.start_rate


#: the ``[connect]`` keys
CONNECT_KEYS = tuple(f.name for f in fields(ConnectLimits))


def connect_limits(table: Mapping[str, Any]) -> ConnectLimits:
    """`ConnectLimits` of a ``[connect]`` table; ValueError ``"key: what"`` (an
    unknown key too)."""
    for key in table:
        if key not in CONNECT_KEYS:
            raise ValueError(f"{key}: unknown key (known: {', '.join(CONNECT_KEYS)})")
    return ConnectLimits(**table)


def network_host(port: object) -> str | None:
    """The host a bus's port connects to (``tcp://``, ``rtu+tcp://``, ``udp://``...,
    pyserial's ``socket://`` and ``rfc2217://``), None for a local port (a device path)."""
    try:
        scheme = url_scheme(port)
    except ValueError:
        return None
    if scheme not in NETWORK_SCHEMES or not isinstance(port, str):
        return None
    try:
        host = urlsplit(port).hostname
    except ValueError:
        return None
    return host.lower() if host else None


class ConnectGate:
    """The bounds of `ConnectLimits` on one event loop: `slot` for each connect."""

    def __init__(self, limits: ConnectLimits) -> None:
        self.limits = limits
        self._all: asyncio.Semaphore | None = None
        self._hosts: dict[str, asyncio.Semaphore] = {}
        self.connecting = 0  # connects in progress now
        self.most = 0  # the most ever in progress at once
        self.waited = 0  # connects that had to wait for a slot
        self._per_host: dict[str, int] = {}  # in progress now, by host
        self.most_per_host: dict[str, int] = {}  # the most at once, by host

    @asynccontextmanager
    async def slot(self, host: str) -> AsyncIterator[None]:
        """Hold a slot of the poller's and one of ``host``'s while connecting."""
        if self._all is None:
            self._all = asyncio.Semaphore(self.limits.max_connecting)
        mine = self._hosts.get(host)
        if mine is None:
            mine = self._hosts[host] = asyncio.Semaphore(self.limits.max_connecting_per_host)
        if mine.locked() or self._all.locked():
            self.waited += 1
        async with mine, self._all:
            self.connecting += 1
            self.most = max(self.most, self.connecting)
            now = self._per_host[host] = self._per_host.get(host, 0) + 1
            self.most_per_host[host] = max(self.most_per_host.get(host, 0), now)
            try:
                yield
            finally:
                self.connecting -= 1
                self._per_host[host] -= 1


__all__ = [
    "CONNECT_KEYS",
    "NETWORK_SCHEMES",
    "ConnectGate",
    "ConnectLimits",
    "connect_limits",
    "network_host",
]
