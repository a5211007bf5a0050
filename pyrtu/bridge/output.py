"""`MqttOutput`: what both MQTT outputs of a bridge configuration (the JSON bridge,
`pyrtu.bridge.bridge.Bridge`; the Sparkplug B edge node,
`pyrtu.sparkplug.node.EdgeNode`) share on top of `OutboxService`: the poller,
report by exception and set commands of the configuration, the outbox of its
``[mqtt]`` table opened with the broker's credentials (`_open_mqtt`), and the
connection loop (`_connector`): connect (`pyrtu.bridge.mqtt.dial`, the shared
back-off), hand the connection to the output (`_connected_to`), wait until it is
lost, clean up (`_link_gone`) and report the loss once per run of failures
(`_broker_lost`)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

from pyrtu.drivers.reconnect import Backoff, Outage, Reconnect

from ..outbox._sync import Flusher
from ..outbox.outbox import Outbox, OutboxLimits
from ..outbox.report import Reporter
from ..outbox.service import OutboxService
from ..poller import Poller
from .commands import CommandQueue
from .config import BridgeConfig
from .mqtt import Credentials, MqttLink, dial
from .topics import Topics
from .writes import SetWriter


class MqttOutput(OutboxService):
    """The base of an MQTT output of ``config`` (``master``: as `Poller`'s).  Each
    output defines `_new_link`, `_connected_to`, `_link_gone`, `_fatal`,
    `_unreachable` and `_broker_lost`, and what `OutboxService` asks for."""

    def __init__(self, config: BridgeConfig, master: Any) -> None:
        self.config = config
        m = config.mqtt
        self.topics = Topics(config)
        self.poller = Poller(config.poller, master=master, changes_only=False)
        points = config.poller.points
        self.reporter = Reporter(points, {p.name: config.max_age(p.name) for p in points})
        self.commands = CommandQueue(m.command_queue, m.write_rate)
        self.writer = SetWriter(self)
        self._outbox: Outbox | None = None
        self._flusher: Flusher | None = None
        self._link: MqttLink | None = None
        self._reconnect = Reconnect(Backoff(m.backoff, m.max_backoff))
        self._credentials: Credentials | None = None
        self._lost_ev: asyncio.Event | None = None  # made in start (loop-bound)
        self._stop: asyncio.Event | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._running = False
        self.fatal: BaseException | None = None

    def _backoff(self) -> Backoff:
        m = self.config.mqtt
        return Backoff(m.backoff, m.max_backoff)

    async def _open_mqtt(self, poll: bool, opened: Callable[[Outbox], None]) -> None:
        """The broker's credentials read (OSError: a file that cannot be used), then
        `OutboxService._open` with the ``[mqtt]`` table's outbox and its limits."""
        m = self.config.mqtt
        self._credentials = Credentials.load(m)
        limits = OutboxLimits(
            max_bytes=m.outbox_max_bytes,
            fsync_interval=m.fsync_interval,
            segment_bytes=min(8 << 20, m.outbox_max_bytes // 4),
            policy="refuse" if m.outbox_policy == "refuse" else "drop-oldest",
        )
        await self._open(m.outbox, limits, poll, opened)

    def _problems(self, what: str, polling: bool) -> list[str]:
        """What keeps the output (``what``: "bridge", "edge node") from doing its
        work, one line each, as both outputs see it: not running, the poller's
        problems (`Poller.health`, when ``polling``), a fatal error, the outbox
        closed, a task not running, the broker not connected (no secret in the
        lines: the broker's URL has none)."""
        if not self._running:
            return [f"the {what} is not running"]
        problems = list(self.poller.health()) if polling else []
        if self.fatal is not None:
            problems.append(f"fatal: {self.fatal}")
        if self._outbox is None:
            problems.append("the outbox is closed")
        for task in self._tasks:
            if task.done():
                problems.append(f"task {task.get_name()} is not running")
        if not self._connected():
            problems.append(f"broker {self.config.mqtt.broker} not connected")
        return problems

    # ------------------------------------------------------------------ the connection

    def _connected(self) -> bool:
        return self._link is not None and self._link.connected

    def _new_link(self) -> MqttLink:
        """A link to the broker for the next attempt (its will, its callbacks)."""
        raise NotImplementedError

    def _connected_to(self, link: MqttLink, outage: Outage | None) -> None:
        """``link`` is connected (``outage``: the one it ends, if any)."""
        raise NotImplementedError

    def _link_gone(self) -> None:
        """The connection ended (or its task failed): forget it, clean up."""
        raise NotImplementedError

    def _fatal(self, error: BaseException) -> None:
        """The broker refused the output for good (`dial`): report it, `_halt`."""
        raise NotImplementedError

    def _unreachable(self, error: BaseException) -> None:
        """The broker cannot be reached (the first failure of a run of them)."""
        raise NotImplementedError

    def _broker_lost(self) -> None:
        """The connection was lost (the first failure of a run of them)."""
        raise NotImplementedError

    async def _connector(self) -> None:
        """Connect, serve the connection until it is lost, again, until stopped or
        halted (the supervised task of the connection)."""
        assert self._lost_ev is not None
        while self._running and self.fatal is None:
            link = await dial(
                self._new_link, self._reconnect, fatal=self._fatal, unreachable=self._unreachable
            )
            if link is None:
                continue
            outage = self._reconnect.recovered(time.monotonic())
            self._link = link
            self._lost_ev.clear()
            self._connected_to(link, outage)
            await self._lost_ev.wait()
            self._link_gone()
            if self._running and self._reconnect.failed(time.monotonic(), "connection lost"):
                self._broker_lost()


__all__ = ["MqttOutput"]
