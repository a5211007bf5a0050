"""`Bridge`: the poller's points to an MQTT broker through the durable outbox, and
set commands back to the drives.

::

    async with Bridge(load_bridge_config("bridge.toml")) as bridge:
        await asyncio.sleep(3600)

The poller hands every value it reads to the `Reporter` (report by exception,
qualities); what is to be published becomes an outbox record, a point update
(`pyrtu.outbox.updates`; its sequence number is the outbox's), made a topic and
a payload when it is published (`Topics.render`), and is published at once when
the broker is connected and nothing older waits, else later from the outbox, in
order, flagged ``historical`` when it waited through an outage (a connection
lost, or a previous run's backlog; not the values read before the first
connection of a run).  The
outbox forgets a record once the broker acknowledged it and everything before it.
A connection that ends is reported once and retried with the shared back-off
(`pyrtu.drivers.reconnect`); the polls go on meanwhile.  On every connection the edge's
``online``, the slaves' states and the latest value of every point the backlog
does not hold are published again (retained): after a broker restart no retained
topic stays missing.

A bus whose port fails (a `PortState` down: a drop unplugged, a TCP peer gone)
has every point republished as ``stale`` and every slave's status ``offline``
while its ``{bus}/status`` topic says ``down`` and why; when the port is back the
bus says ``up``, each point comes back ``good`` with its next read and each slave
``online`` with its first value (or, if it no longer answers, stays ``offline``
when the poller says so).

With ``messages = "device"`` the records are published in device messages
(`_take`): the records handed over in one pump, consecutive records of one slave
(no point twice, at most `_PER_MESSAGE`) in one message, acknowledged together
(`DeliveryWindow.sent_group`); the live values are pumped at the end of the
loop's turn, so that a poll's changes, which the poller delivers in one turn,
make one message.

Every background task (the connection, the stats, the writers) is supervised: a
failure is logged once with its cause, reported (``task_failed``), counted and the
task started again after the shared back-off (`pyrtu.drivers.supervise`).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pyrtu.drivers.reconnect import Outage
from pyrtu.drivers.supervise import cause

from ..outbox.outbox import Outbox, OutboxError
from ..outbox.updates import PointUpdate
from ..poller import PointDropped, PortState, SlaveState, TaskFailed, Update
from .config import BridgeConfig, load_bridge_config
from .delivery import DeliveryWindow
from .mqtt import MqttLink
from .output import MqttOutput
from .topics import OFFLINE, ONLINE, Unpublishable, bus_payload, device_payload, payload

log = logging.getLogger("pyrtu.bridge")

_LIVE = 8192  # records kept in memory for the live path (more: read back from disk)
_BATCH = 512  # records read from the outbox at a time
_PER_MESSAGE = 1000  # the most points of one device message (messages = "device")


@dataclass(frozen=True, slots=True)
class BridgeEvent:
    """Something the bridge reports: ``kind`` is ``broker_down``, ``broker_up``,
    ``port``, ``slave``, ``dropped``, ``outbox_error``, ``quarantined``, ``task_failed`` (a
    background task raised: ``task``, ``error``, ``retry_in`` seconds), ``fatal``
    or ``stats``."""

    kind: str
    time: float
    detail: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"event": self.kind, "time": round(self.time, 6), **self.detail}


class Bridge(MqttOutput):
    """The bridge of one edge (see the module docstring).  ``config``: a
    `BridgeConfig` or a TOML path; ``master``: as `Poller`'s."""

    WHAT = "the bridge"

    def __init__(self, config: BridgeConfig | str, *, master: Any = "auto") -> None:
        if isinstance(config, str):
            config = load_bridge_config(config)
        super().__init__(config, master)
        self._window = DeliveryWindow(config.mqtt.inflight)
        #: (seq, record, its update, when read) of the records not yet published
        self._live: deque[tuple[int, bytes, PointUpdate, float]] = deque()
        self._live_base = 0  # every record from this seq on is in _live or published
        self._cursor = 0  # the last seq handed to the client on this connection
        self._historical_below = 0  # records below this seq are published as historical
        self._start_seq = 0  # records below it are a previous run's (historical)
        self._was_connected = False  # a connection of this run existed (then was lost)
        self._latest: dict[str, tuple[int, PointUpdate]] = {}  # point -> the last appended
        self._slaves: dict[tuple[str, int], bool] = {}
        self._ports: dict[str, PortState] = {}  # the last port event of each bus
        self._port_down: set[str] = set()
        # buses whose "up" and slaves whose "online" wait for their first value
        self._bus_unseen: set[str] = {b.name for b in config.poller.buses}
        self._resume: set[tuple[str, int]] = set()
        self._event_cbs: list[Callable[[BridgeEvent], None]] = []
        self._polling = False  # start(poll=True): the poller runs
        self._ack_pending = False
        self._acked_seq = 0  # every record up to this seq is acknowledged
        self._t0 = time.monotonic()
        self.appended = 0
        self.refused = 0  # updates the outbox did not accept (disk full, budget)
        self._outbox_down = False
        self.reconnects = 0
        self.publish_errors = 0
        self._quarantined_topics: set[str] = set()  # reported once each
        self.task_failures = 0  # background tasks that raised (each restarted)
        self.final_stats: dict[str, Any] = {}
        # messages = "device": the device message being made (`_take`), its topic,
        # its records (seq, record, when read), its entries and their points' names
        self._grouped = config.mqtt.messages == "device"
        self._group: list[tuple[int, bytes, float]] = []
        self._group_topic = ""
        self._group_entries: list[bytes] = []
        self._group_points: set[str] = set()
        self._pump_soon: asyncio.Handle | None = None  # the live values' pump, this turn

    # ------------------------------------------------------------------ life cycle

    async def start(self, poll: bool = True) -> None:
        """Open the outbox, start the poller (PortError when a port fails) and the
        connection to the broker (in the background: a broker that is down only
        delays publishing).  OutboxError when the outbox cannot be opened.
        ``poll=False``: no poller; values come through `feed`."""
        if self._running:
            return
        await self._open_mqtt(poll, self._opened)
        self._polling = poll
        self._running = True
        self._t0 = time.monotonic()
        self._tasks = [
            self._supervise("pyrtu-bridge-mqtt", self._connector, self._link_gone),
            self._supervise("pyrtu-bridge-stats", self._stats_loop),
        ]

    def _opened(self, ob: Outbox) -> None:
        self._live_base = self._start_seq = ob.next_seq
        self._was_connected = False
        self._acked_seq = ob.acked

    async def stop(self, drain: float = 5.0) -> None:
        """Stop polling, publish what waits (up to ``drain`` seconds while the broker
        is connected), say ``offline``, disconnect, flush and close the outbox."""
        if not self._running:
            return
        self._running = False
        await self.poller.stop()
        await self.writer.stop()
        ob, flusher = self._outbox, self._flusher
        assert ob is not None and flusher is not None
        flusher.submit()
        end = time.monotonic() + drain
        while self._connected() and ob.depth > 0 and time.monotonic() < end:
            self._pump()
            await asyncio.sleep(0.01)
            flusher.submit()
        await self._cancel_tasks()
        if self._pump_soon is not None:
            self._pump_soon.cancel()
            self._pump_soon = None
        link = self._link
        if link is not None and link.connected:
            link.publish(self.topics.edge_status, OFFLINE, 1, True)
            for _ in range(50):  # let the offline status out before DISCONNECT
                if link.pending_writes == 0:
                    break
                await asyncio.sleep(0.002)
            link.close(graceful=True)
        self._link = None
        self._commit_acks()
        await self._close_outbox(self._final_stats)

    def _final_stats(self) -> None:
        self.final_stats = self.stats()

    def on_event(self, callback: Callable[[BridgeEvent], None]) -> None:
        """Call ``callback(event)`` for every `BridgeEvent` (on the loop)."""
        self._event_cbs.append(callback)

    # ------------------------------------------------------------------ supervision

    def task_failed(
        self, task: str, error: BaseException, retry_in: float, first: bool = True
    ) -> None:
        """A background task raised ``error``; it starts again in ``retry_in``
        seconds.  Counted always; the ``first`` failure of a run of failures (as
        `Reconnect.failed` says) is reported: one log line with the cause and a
        `task_failed` event (the next ones at debug level, as retries are)."""
        self.task_failures += 1
        text = cause(error)
        log.debug("bridge: task %s failed", task, exc_info=error)
        if not first:
            log.debug("bridge: task %s failed again: %s", task, text)
            return
        log.error("bridge: task %s failed: %s (restarting in %.2f s)", task, text, retry_in)
        self._emit("task_failed", task=task, error=text, retry_in=round(retry_in, 3))

    def _emit(self, kind: str, **detail: Any) -> None:
        ev = BridgeEvent(kind, time.time(), detail)
        for cb in self._event_cbs:
            try:
                cb(ev)
            except Exception:
                log.exception("bridge event callback %r failed", cb)

    # ------------------------------------------------------------------ the poller's side

    def feed(self, ev: Any) -> None:
        """Take a poller event (`Update`, `SlaveState`, `PointDropped`, `PortState`,
        `TaskFailed`); the poller's callback, also for values from elsewhere."""
        now = time.monotonic()
        if type(ev) is Update:
            p = ev.point
            if self._bus_unseen or self._resume:
                self._first_value(p.bus, p.slave)
            if self.reporter.update(p, ev.value, ev.time, now):
                self._append(p, ev.value, ev.time, ev.quality)
        elif isinstance(ev, SlaveState):
            self._slaves[(ev.bus, ev.slave)] = ev.online
            self._resume.discard((ev.bus, ev.slave))
            for p, v, t, q in self.reporter.slave_state(ev.bus, ev.slave, ev.online, now):
                self._append(p, v, t, q)
            self._publish_slave(ev.bus, ev.slave, ev.online)
            self._emit("slave", bus=ev.bus, slave=ev.slave, online=ev.online)
        elif isinstance(ev, PointDropped):
            p, v, t, q = self.reporter.dropped(ev.point, ev.time, now)
            self._append(p, v, t, q)
            self._emit("dropped", point=ev.point.name, reason=ev.reason)
        elif isinstance(ev, PortState):
            self._port(ev, now)
        elif isinstance(ev, TaskFailed):  # logged and counted by the poller (its summary)
            self._emit("task_failed", task=ev.task, error=ev.error,
                       retry_in=round(ev.retry_in, 3), bus=ev.bus)  # fmt: skip

    def _port(self, ev: PortState, now: float) -> None:
        """A bus's port failed or is back (see the module docstring)."""
        bus = ev.bus
        self._ports[bus] = ev
        self._bus_unseen.discard(bus)
        mine = [k for k in self.topics.slave_status if k[0] == bus]
        if not ev.up:
            self._port_down.add(bus)
            self._resume.difference_update(mine)
            for p, v, t, q in self.reporter.bus_down(bus, now):
                self._append(p, v, t, q)
            for _, slave in mine:
                self._publish_slave(bus, slave, False)
        else:
            self._port_down.discard(bus)
            # the slaves online before the outage: online again with their first value
            self._resume.update(k for k in mine if self._slaves.get(k))
        self._publish_bus(bus)
        self._emit("port", bus=bus, port=ev.port, up=ev.up, error=ev.error)

    def _first_value(self, bus: str, slave: int) -> None:
        """A value read: the bus's port works, the slave answers."""
        if bus in self._bus_unseen:
            self._bus_unseen.discard(bus)
            self._publish_bus(bus)
        if (bus, slave) in self._resume:
            self._resume.discard((bus, slave))
            self._publish_slave(bus, slave, True)

    def _slave_shown(self, bus: str, slave: int) -> bool:
        """What a slave's status topic says: online when the poller says so, the
        bus's port is up and, after an outage, the slave answered again."""
        return (
            self._slaves.get((bus, slave), False)
            and bus not in self._port_down
            and (bus, slave) not in self._resume
        )

    def _publish_bus(self, bus: str) -> None:
        link = self._link
        t = self.topics.bus_status.get(bus)
        if link is None or not link.connected or t is None or bus in self._bus_unseen:
            return
        ev = self._ports.get(bus)
        port = str(next(b.port for b in self.config.poller.buses if b.name == bus))
        if ev is None:  # values came, no outage yet
            doc = bus_payload("up", port, "", None, time.time())
        else:
            doc = bus_payload("up" if ev.up else "down", ev.port, ev.error, ev.since, ev.time)
        link.publish(t, doc, 1, True)

    def _store_refused(self, error: Exception) -> None:
        self.refused += 1
        if not self._outbox_down:
            self._outbox_down = True
            log.error("bridge: the outbox refuses updates: %s", error)
            self._emit("outbox_error", message=str(error))

    def _stored(self, seq: int, rec: bytes, update: PointUpdate) -> None:
        if self._outbox_down:
            self._outbox_down = False
            log.warning("bridge: the outbox accepts updates again")
        self.appended += 1
        self._latest[update.point] = (seq, update)
        live = self._live
        read_at = time.time() if update.time is None else update.time
        live.append((seq, rec, update, read_at))
        if len(live) > _LIVE:
            live.popleft()
            self._live_base = live[0][0]
        if not self._grouped:
            self._pump()
        elif self._pump_soon is None:  # at the end of the turn: the poll's other values
            self._pump_soon = asyncio.get_running_loop().call_soon(self._pump_live)

    def _pump_live(self) -> None:
        self._pump_soon = None
        self._pump()

    # ------------------------------------------------------------------ publishing

    def _pump(self) -> None:
        """Hand records to the client in sequence order while the window has room
        (in device messages with ``messages = "device"``: `_take`), and write them
        to the socket at once (`MqttLink.write_now`)."""
        link = self._link
        if link is None or not link.connected:
            return
        win = self._window
        qos = self.config.mqtt.qos
        live = self._live
        ob = self._outbox
        assert ob is not None
        grouped = self._grouped
        send = self._take if grouped else self._send
        while self._room():
            while live and live[0][0] <= self._cursor:
                live.popleft()
            if self._cursor + 1 >= self._live_base:
                if not live:
                    break
                seq, rec, update, read_at = live.popleft()
                send(link, seq, rec, read_at, qos, update)
                continue
            wanted = _BATCH if grouped else min(_BATCH, win.window - len(win))
            batch = ob.pending(wanted, after=self._cursor)
            if not batch:
                break  # the rest is not durable yet: after the next flush
            for seq, rec in batch:
                if seq >= self._live_base:
                    # nothing older is left on disk (dropped): _live has the rest
                    self._cursor = max(self._cursor, self._live_base - 1)
                    break
                if grouped and not self._room():
                    break
                send(link, seq, rec, 0.0, qos)
        if grouped:
            self._publish_group(link, qos)
        # to the kernel now: a live value waits for no timer and no other task
        link.write_now()

    def _room(self) -> bool:
        """Room in the window for one more publication (the device message being
        made counts as one)."""
        win = self._window
        return len(win) + (1 if self._group else 0) < win.window

    def _send(
        self,
        link: MqttLink,
        seq: int,
        rec: bytes,
        read_at: float,
        qos: int,
        update: PointUpdate | None = None,
    ) -> None:
        """Publish a record (``update``: what it holds, when known): its topic and
        payload made now (`Topics.render`)."""
        topics = self.topics
        try:
            topic, body = topics.render(rec) if update is None else topics.render_update(update)
        except Unpublishable as e:
            self._set_aside(seq, rec, str(e), e.topic)
            return
        try:
            mid = link.publish(topic, payload(body, seq, seq < self._historical_below), qos, True)
        except ValueError as e:  # the client refuses it (its size, its topic): for ever
            self._set_aside(seq, rec, f"the MQTT client refuses it: {e}", topic)
            return
        self._cursor = seq
        if mid < 0:
            self.publish_errors += 1
            return
        self._window.sent(seq, mid, read_at, rec)

    def _take(
        self,
        link: MqttLink,
        seq: int,
        rec: bytes,
        read_at: float,
        qos: int,
        update: PointUpdate | None = None,
    ) -> None:
        """Put a record (``update``: what it holds, when known) in the device
        message being made (``messages = "device"``), which is published first when
        the record is another slave's, or of a point it holds already, or would make
        it longer than `_PER_MESSAGE`; or when the record is to be set aside (so
        that the window's order stays the outbox's).  An earlier pyrtu's record
        (a topic and a payload) is published as it was (`_send`)."""
        topics = self.topics
        try:
            if update is None:
                update = topics.update(rec)
                if update is None:
                    self._publish_group(link, qos)
                    self._send(link, seq, rec, read_at, qos)
                    return
            body = topics.render_update(update)[1]
        except Unpublishable as e:
            self._publish_group(link, qos)
            self._set_aside(seq, rec, str(e), e.topic)
            return
        name = update.point
        device = topics.device_of[name]
        if self._group and (
            device != self._group_topic
            or name in self._group_points
            or len(self._group) >= _PER_MESSAGE
        ):
            self._publish_group(link, qos)
        self._group_topic = device
        self._group_points.add(name)
        self._group.append((seq, rec, read_at))
        entry = payload(body, seq, seq < self._historical_below)
        self._group_entries.append(topics.json_name[name] + b":" + entry)
        self._cursor = seq

    def _publish_group(self, link: MqttLink, qos: int) -> None:
        """Publish the device message being made (not retained: it holds the
        changes of a poll, not the device's state), if any."""
        group = self._group
        if not group:
            return
        topic, entries = self._group_topic, self._group_entries
        self._group, self._group_entries, self._group_points = [], [], set()
        records = [(seq, rec) for seq, rec, _ in group]
        try:
            mid = link.publish(topic, device_payload(entries), qos, False)
        except ValueError as e:  # the client refuses it (its size): for ever
            for seq, rec in records:
                self._set_aside(seq, rec, f"the MQTT client refuses it: {e}", topic)
            return
        if mid < 0:
            self.publish_errors += 1
            return
        self._window.sent_group(mid, group[0][2], records)

    def _set_aside(self, seq: int, rec: bytes, problem: str, topic: str) -> None:
        """A record that can never be published: quarantined, and passed by as if
        delivered."""
        self._cursor = seq
        self._keep_aside(seq, rec, problem, topic)
        if self._window.skipped(seq) and not self._ack_pending:
            self._ack_pending = True
            asyncio.get_running_loop().call_soon(self._commit_acks)

    def _on_refused(self, mid: int, reason: str) -> None:
        """The broker refused a publication (its acknowledgement follows): a record's
        is quarantined, not counted as delivered and forgotten."""
        for seq, rec in self._window.records(mid):
            self._keep_aside(seq, rec, f"the broker refused it: {reason}", self.topics.name(rec))

    def _keep_aside(self, seq: int, rec: bytes, problem: str, topic: str) -> None:
        """Copy a record aside (`Outbox.quarantine`), counted, reported once per
        ``topic`` (what the report calls it)."""
        ob = self._outbox
        assert ob is not None
        try:
            ob.quarantine(seq, rec, problem)
        except OutboxError as e:  # it cannot be kept either: said, and passed by
            log.error("bridge: record %d (%r) cannot be published (%s) nor set aside: %s",
                      seq, topic, problem, e)  # fmt: skip
            self._emit("outbox_error", message=str(e))
        else:
            if topic not in self._quarantined_topics and len(self._quarantined_topics) < 64:
                self._quarantined_topics.add(topic)
                log.error("bridge: record %d (%r) cannot be published: %s; set aside in %s",
                          seq, topic, problem, ob.quarantine_path)  # fmt: skip
                self._emit("quarantined", seq=seq, topic=topic, reason=problem,
                           file=str(ob.quarantine_path))  # fmt: skip

    def _on_ack(self, mid: int) -> None:
        if self._window.acked(mid, time.time()) and not self._ack_pending:
            self._ack_pending = True
            asyncio.get_running_loop().call_soon(self._commit_acks)

    def _commit_acks(self) -> None:
        self._ack_pending = False
        c = self._window.contiguous
        ob = self._outbox
        if c is not None and ob is not None and c > self._acked_seq:
            self._acked_seq = c
            ob.ack(c)
            if self._flusher is not None:
                self._flusher.poke()
        self._pump()

    def _flushed(self, error: OutboxError | None) -> None:
        """A batch of the outbox's fsyncs is done (on its thread): its records may be
        published from the outbox now; an error is reported once."""
        if error is None:
            self._pump()
        elif not self._outbox_down:
            self._outbox_down = True
            log.error("bridge: outbox flush failed: %s", error)
            self._emit("outbox_error", message=str(error))

    def _publish_slave(self, bus: str, slave: int, online: bool) -> None:
        link = self._link
        if link is not None and link.connected:
            t = self.topics.slave_status.get((bus, slave))
            if t is not None:
                link.publish(t, ONLINE if online else OFFLINE, 1, True)

    # ------------------------------------------------------------------ the connection

    def _new_link(self) -> MqttLink:
        return MqttLink(
            self.config.mqtt,
            self.topics.edge_status,
            on_message=self.writer.on_message,
            on_ack=self._on_ack,
            on_lost=self._on_lost,
            credentials=self._credentials,
            on_refused=self._on_refused,
        )

    def _unreachable(self, e: BaseException) -> None:
        broker = self.config.mqtt.broker
        log.warning("bridge: broker %s unreachable: %s (retrying)", broker, e)
        self._emit("broker_down", broker=broker, error=str(e) or type(e).__name__)

    def _connected_to(self, link: MqttLink, outage: Outage | None) -> None:
        broker = self.config.mqtt.broker
        if outage is not None:
            log.warning("bridge: broker %s back after %.1f s", broker, outage.duration or 0)
        self.reconnects += 1
        self._on_connected(link)
        self._emit(
            "broker_up",
            broker=broker,
            down_s=None if outage is None else round(outage.duration or 0, 3),
        )

    def _broker_lost(self) -> None:
        broker = self.config.mqtt.broker
        log.warning("bridge: lost the broker %s (retrying)", broker)
        self._emit("broker_down", broker=broker, error="connection lost")

    def _link_gone(self) -> None:
        """The connection ended (or its task failed): what was handed to the client
        and not acknowledged comes from the outbox on the next one."""
        link, self._link = self._link, None
        if link is not None and link.connected:  # the task failed, the socket did not
            link.close(graceful=False)
        self._window.reset()
        live = self._live
        self._live_base = max(self._live_base, live[0][0] if live else self._next_seq())

    def _next_seq(self) -> int:
        return self._outbox.next_seq if self._outbox is not None else 0

    def _fatal(self, e: BaseException) -> None:
        """The broker refused the bridge for good (`dial`): reported, halted."""
        log.error("bridge: %s", e)
        self._emit("fatal", message=str(e))
        self._halt(e)

    def _on_connected(self, link: MqttLink) -> None:
        """Status, slaves, the latest values the backlog does not hold, subscriptions,
        then the backlog and the live records."""
        ob = self._outbox
        assert ob is not None
        link.publish(self.topics.edge_status, ONLINE, 1, True)
        for bus in self.topics.bus_status:
            self._publish_bus(bus)
        for bus, slave in self.topics.slave_status:
            if (bus, slave) in self._slaves or bus in self._port_down:
                self._publish_slave(bus, slave, self._slave_shown(bus, slave))
        self._acked_seq = max(self._acked_seq, ob.acked)  # past what drop-oldest dropped
        self._cursor = self._acked_seq
        oldest = self._acked_seq + 1
        # historical: what waited through an outage, that is a connection of this
        # run lost, or the bridge itself not running (a previous run's backlog);
        # the values read since start-up are live on the first connection
        self._historical_below = ob.next_seq if self._was_connected else self._start_seq
        self._was_connected = True
        qos = self.config.mqtt.qos
        # delivered before: published again for the retained copy (device messages
        # are not retained: none is published twice)
        for seq, update in () if self._grouped else self._latest.values():
            if seq < oldest:
                topic, body = self.topics.render_update(update)
                link.publish(topic, payload(body, seq, False), qos, True)
        if self.config.mqtt.discovery:
            from .discovery import configs

            for topic, doc in configs(self.config, self.topics):
                link.publish(topic, doc, 1, True)
        subs = [self.topics.set_filter, *self.topics.extra_set_topics()]
        link.subscribe(subs)
        self.writer.connected(link)
        self._pump()

    # ------------------------------------------------------------------ figures

    def stats(self) -> dict[str, Any]:
        """The bridge's figures (JSON-ready; no secret in them)."""
        ob = self._outbox
        win = self._window
        now = time.monotonic()
        p50, p99 = win.latency(50), win.latency(99)
        oldest = ob.oldest_time if ob is not None else None
        return {
            "edge": self.config.mqtt.edge,
            "seconds": round(now - self._t0, 3),
            "connected": self._connected(),
            "broker": self.config.mqtt.broker,
            "updates": self.appended,
            "published": win.published,
            "acknowledged": win.acknowledged,
            "outbox_depth": ob.depth if ob is not None else 0,
            "outbox_bytes": ob.bytes_used if ob is not None else 0,
            "oldest_unsent_s": None if oldest is None else round(max(0.0, now - oldest), 3),
            "publish_latency_p50_ms": None if p50 is None else round(p50 * 1e3, 3),
            "publish_latency_p99_ms": None if p99 is None else round(p99 * 1e3, 3),
            "drops": (ob.dropped if ob is not None else 0) + self.refused,
            "quarantined": ob.quarantined if ob is not None else 0,
            "connections": self.reconnects,
            "outages": self._reconnect.outages,
            "task_failures": self.task_failures,
            "commands": self.writer.stats(),
            "buses": [r.as_dict() for r in self.poller.report()],
        }

    def health(self) -> list[str]:
        """What keeps the bridge from doing its work, one line each (empty: it
        polls, its tasks run, the outbox is open and the broker connected): the
        poller's problems (`Poller.health`), a fatal error, the broker not
        connected (no secret in the lines: the broker's URL has none)."""
        return self._problems("bridge", self._polling)

    async def _stats_loop(self) -> None:
        import json

        every = self.config.mqtt.stats_interval
        while True:
            await asyncio.sleep(every)
            doc = self.stats()
            link = self._link
            if link is not None and link.connected:
                link.publish(self.topics.stats, json.dumps(doc).encode(), 0, False)
            self._emit("stats", **doc)


__all__ = ["Bridge", "BridgeEvent"]
