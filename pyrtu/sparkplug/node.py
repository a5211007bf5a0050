"""`EdgeNode`: `pyrtu bridge` as a Sparkplug B 3.0 edge node, on the poller, the
shared durable outbox (`pyrtu.outbox`) and one MQTT connection.

::

    async with EdgeNode(load_sparkplug_config("bridge.toml")) as node:
        await asyncio.sleep(3600)

Every connection: a clean session whose will is the NDEATH (QoS 1, not retained)
with a new bdSeq (`BdSeqStore`); the node subscribes to its NCMD and DCMD topics
(and the primary host's STATE), then, at once or, with a primary host, when its
STATE says online (a timestamp older than the last one accepted is ignored),
publishes the NBIRTH (seq 0, bdSeq, ``Node Control/Rebirth``) and a DBIRTH for each
device not known dead (every one at first, a metric never read yet ``is_null``;
then one whose slave answers and port is up), all QoS 0, never retained.

The poller's values go through the `Reporter` (report by exception) into the
outbox as point updates.  A value read while the node is born and nothing older
waits is published at the end of the loop's turn (DDATA, by alias, QoS 0; the
turn's live values of one device in one message); everything else waits in the
outbox and is published in order once the node is born again, flagged
``is_historical`` (it is older than the values the births carry).  A record is
released from the outbox once the broker has confirmed it: QoS 0 has no
acknowledgement, so after a publication the node sends an UNSUBSCRIBE of a filter
it never subscribed to (`BARRIER`), and its UNSUBACK, which a broker sends after
handling every packet before it on the connection, confirms every record
published before it (one such barrier awaits its answer at a time).  Records not
confirmed when the connection ends (written to a socket the broker never read)
are published again after the next births, historical, in order.  A slave that stops
answering, or a port that fails, gets a DDEATH; its first value afterwards a
DBIRTH.  Records of a device that is dead when their turn comes are passed by
(``unforwarded``: a DDATA of a dead device would break the session's rules).

NCMD ``Node Control/Rebirth`` = true: NBIRTH and every DBIRTH again (the stored
backlog follows, still historical).  DCMD: each metric (by name or alias) is
checked against its datatype, then goes through the bridge's set path
(`SetWriter.command`: writable, range, queue, rate limit, expiry, write,
read-back): the value read back is published in the next DDATA.  Refusals are
logged and counted (``dcmd_refused``, per reason).

When the primary host goes offline the node publishes its NDEATH, disconnects
(MQTT 5: "Disconnect with Will Message") and connects again, to wait for the host.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import paho.mqtt.client as paho

from pyrtu.drivers.reconnect import Outage
from pyrtu.drivers.supervise import cause

from ..bridge.mqtt import MqttLink
from ..bridge.output import MqttOutput
from ..outbox.outbox import Outbox, OutboxError
from ..outbox.updates import PointUpdate, UpdateError, decode_update
from ..poller import Point, PointDropped, PortState, SlaveState, TaskFailed, Update
from ..poller.points import Value
from .config import SparkplugConfig
from .metrics import NODE_REBIRTH, DeviceDef, MetricDef, get_value
from .payload import payload_class
from .session import BdSeqStore, EdgeSession, HostState, LatestValue

log = logging.getLogger("pyrtu.sparkplug")

_BATCH = 64  # records of the backlog published per turn of the loop
_PER_MESSAGE = 64  # metrics per DDATA of the backlog
#: the topic filter the node unsubscribes from (never subscribed to) to have the
#: broker confirm what it published before (see the module doc)
BARRIER = "pyrtu/sparkplug/delivered"


class EdgeNode(MqttOutput):
    """The Sparkplug edge node of one bridge configuration (see the module doc)."""

    WHAT = "the edge node"

    def __init__(self, config: SparkplugConfig, *, master: Any = "auto") -> None:
        self.spb = config
        super().__init__(config.bridge, master)
        self.session = EdgeSession(config)
        self.host = HostState()
        self._bdseq = BdSeqStore(config.bdseq_file)
        self._latest: dict[str, LatestValue] = {}
        #: devices not known dead (every one at first: the NBIRTH is followed by every
        #: DBIRTH, tck-id-payloads-dbirth-order; a slave that does not answer gets its
        #: DDEATH when the poller says so)
        self._alive: set[str] = {d.id for d in config.devices}
        self._offline: set[tuple[str, int]] = set()  # slaves the poller says offline
        self._port_down: set[str] = set()
        self._born = False  # NBIRTH published on this connection
        self._dborn: set[str] = set()  # devices with a DBIRTH since the NBIRTH
        self._cursor = 0  # every record up to this seq is published or passed by
        #: the barrier awaiting its answer: (its link, its mid, the cursor it confirms)
        self._barrier: tuple[MqttLink, int, int] | None = None
        self._live: list[tuple[int, PointUpdate]] = []  # live values of this turn
        self._live_soon: asyncio.Handle | None = None
        self._live_from = 0  # records below this seq are historical
        self._pump_soon: asyncio.Handle | None = None  # the next batch of the backlog
        self.counts: dict[str, int] = {
            "connects": 0, "nbirth": 0, "dbirth": 0, "ddeath": 0, "ddata": 0,
            "metrics_live": 0, "metrics_historical": 0, "unforwarded": 0, "rebirths": 0,
            "host_offline": 0, "dcmd": 0, "refused": 0, "task_failures": 0, "foreign_records": 0,
        }  # fmt: skip
        self.dcmd_refused: dict[str, int] = {}

    # ------------------------------------------------------------------ life cycle

    async def start(self, poll: bool = True) -> None:
        """Open the outbox, start the poller and the connection (in the background)."""
        if self._running:
            return
        self._bdseq.load()  # a damaged file refused now, not at the first connect
        await self._open_mqtt(poll, self._opened)
        self._running = True
        self._tasks = [self._supervise("pyrtu-sparkplug-mqtt", self._connector, self._link_gone)]

    def _opened(self, ob: Outbox) -> None:
        self._cursor = ob.acked
        self._live_from = ob.next_seq

    async def stop(self) -> None:
        """Stop polling; NDEATH, disconnect; flush and close the outbox."""
        if not self._running:
            return
        self._running = False
        await self.poller.stop()
        await self.writer.stop()
        await self._cancel_tasks()
        link = self._link
        if link is not None and link.connected:
            await self._confirmed(link, 2.0)
            self._say_death(link)
            for _ in range(100):
                if link.pending_writes == 0:
                    break
                await asyncio.sleep(0.002)
            link.close(graceful=True, with_will=True)
        self._link = None
        await self._close_outbox()

    def task_failed(
        self, task: str, error: BaseException, retry_in: float, first: bool = True
    ) -> None:
        """A background task raised; it starts again in ``retry_in`` s (logged once
        per run of failures, counted always)."""
        self.counts["task_failures"] += 1
        level = logging.ERROR if first else logging.DEBUG
        log.log(level, "sparkplug: task %s failed: %s (restarting in %.2f s)",
                task, cause(error), retry_in)  # fmt: skip

    # ------------------------------------------------------------------ the poller's side

    def feed(self, ev: Any) -> None:
        """A poller event (`Update`, `SlaveState`, `PointDropped`, `PortState`)."""
        now = time.monotonic()
        if type(ev) is Update:
            p = ev.point
            self._latest[p.name] = LatestValue(
                ev.value, ev.time, "bad" if ev.value is None else "good"
            )
            self._device_answers(p.bus, p.slave)
            if self.reporter.update(p, ev.value, ev.time, now):
                self._append(p, ev.value, ev.time, ev.quality)
        elif isinstance(ev, SlaveState):
            key = (ev.bus, ev.slave)
            if ev.online:
                self._offline.discard(key)
            else:
                self._offline.add(key)
                for p, v, t, q in self.reporter.slave_state(ev.bus, ev.slave, False, now):
                    self._append(p, v, t, q)
                self._device_dead(ev.bus, ev.slave)
        elif isinstance(ev, PointDropped):
            p, v, t, q = self.reporter.dropped(ev.point, ev.time, now)
            self._latest[p.name] = LatestValue(v, t, q)
            self._append(p, v, t, q)
        elif isinstance(ev, PortState):
            if ev.up:
                self._port_down.discard(ev.bus)
            else:
                self._port_down.add(ev.bus)
                for p, v, t, q in self.reporter.bus_down(ev.bus, now):
                    self._append(p, v, t, q)
                for d in self.spb.devices:
                    if d.bus == ev.bus:
                        self._device_dead(d.bus, d.slave)
        elif isinstance(ev, TaskFailed):
            log.error("sparkplug: poller task %s failed: %s", ev.task, ev.error)

    def _device_answers(self, bus: str, slave: int) -> None:
        dev = self.session.by_slave.get((bus, slave))
        if dev is None or dev.id in self._alive or bus in self._port_down:
            return
        self._offline.discard((bus, slave))
        self._alive.add(dev.id)
        if self._born:
            self._publish_dbirth(dev)

    def _device_dead(self, bus: str, slave: int) -> None:
        dev = self.session.by_slave.get((bus, slave))
        if dev is None or dev.id not in self._alive:
            return
        self._flush_live()  # its last values (stale) before its DDEATH
        self._alive.discard(dev.id)
        link = self._link
        if self._born and dev.id in self._dborn and link is not None and link.connected:
            self._dborn.discard(dev.id)
            link.publish(
                self.session.topic("DDEATH", dev), self.session.ddeath(time.time()), 0, False
            )
            link.write_now()
            self.counts["ddeath"] += 1

    def publish_value(self, point: Point, value: Value | None, read_at: float) -> None:
        """A write's read-back: published in the next DDATA whatever its deadband."""
        self._latest[point.name] = LatestValue(value, read_at, "bad" if value is None else "good")
        super().publish_value(point, value, read_at)

    def _store_refused(self, error: Exception) -> None:
        self.counts["refused"] += 1
        log.error("sparkplug: the outbox refuses an update: %s", error)

    def _stored(self, seq: int, rec: bytes, update: PointUpdate) -> None:
        link = self._link
        after = self._live[-1][0] if self._live else self._cursor
        if self._born and seq == after + 1 and link is not None and link.connected:
            # live: at the end of this turn of the loop (not after the fsync), with
            # the turn's other live values in as few DDATA as the devices allow
            self._live.append((seq, update))
            if self._live_soon is None:
                self._live_soon = asyncio.get_running_loop().call_soon(self._publish_live)

    def _flush_live(self) -> None:
        """The live values waiting for the end of the turn, now (before a birth or
        a death, which must follow them)."""
        if self._live_soon is not None:
            self._live_soon.cancel()
            self._publish_live()

    def _publish_live(self) -> None:
        """The live values of this turn, unless the pump or a lost connection came
        first (those the pump published are not published again)."""
        self._live_soon = None
        batch, self._live = self._live, []
        link = self._link
        if not self._born or link is None or not link.connected:
            return
        batch = [(seq, u) for seq, u in batch if seq > self._cursor]
        if not batch or batch[0][0] != self._cursor + 1:
            return  # the pump publishes them, in order
        self._publish_records(batch, link)
        self._confirm(link)

    # ------------------------------------------------------------------ publishing

    def _flushed(self, error: OutboxError | None) -> None:
        if error is not None:
            log.error("sparkplug: outbox flush failed: %s", error)
            return
        if self._pump_soon is None:
            self._pump()

    def _pump(self) -> None:
        """Publish what waits in the outbox, in order, while the node is born: one
        batch per turn of the loop (a long backlog never holds the loop, and a
        command that comes meanwhile, a Rebirth, is served between two batches),
        the next once the socket took the last."""
        self._pump_soon = None
        link, ob = self._link, self._outbox
        if not self._born or link is None or not link.connected or ob is None:
            return
        if link.pending_writes > _BATCH:  # the kernel's buffer is full: later
            self._pump_soon = asyncio.get_running_loop().call_later(0.005, self._pump)
            return
        batch = ob.pending(_BATCH, after=self._cursor)
        if not batch:
            return
        self._publish_records(batch, link)
        self._confirm(link)
        if len(batch) == _BATCH:
            self._pump_soon = asyncio.get_running_loop().call_soon(self._pump)

    def _confirm(self, link: MqttLink) -> None:
        """Have the broker confirm what was published up to the cursor (a barrier,
        see the module doc), unless a barrier awaits its answer already (its answer
        sends the next one) or nothing waits for confirmation."""
        ob, client = self._outbox, link.client
        if self._barrier is not None or ob is None or client is None or not link.connected:
            return
        if self._cursor <= ob.acked:
            return
        client.on_unsubscribe = self._barrier_answered
        rc, mid = client.unsubscribe(BARRIER)
        if rc == paho.MQTT_ERR_SUCCESS and mid is not None:
            self._barrier = (link, mid, self._cursor)

    def _barrier_answered(
        self, client: Any, userdata: Any, mid: int, reasons: Any, props: Any
    ) -> None:
        """The broker's UNSUBACK: every record up to the barrier's cursor is confirmed."""
        barrier, ob = self._barrier, self._outbox
        if barrier is None or barrier[1] != mid or barrier[0].client is not client:
            return
        self._barrier = None
        if ob is not None:
            ob.ack(barrier[2])
            if self._flusher is not None:
                self._flusher.poke()
        link = self._link
        if link is barrier[0]:
            self._confirm(link)

    async def _confirmed(self, link: MqttLink, patience: float) -> None:
        """Until the broker has confirmed every record published (at most
        ``patience`` s: what is not confirmed then is published again next time)."""
        ob = self._outbox
        give_up = time.monotonic() + patience
        while ob is not None and link.connected and time.monotonic() < give_up:
            self._confirm(link)
            if self._barrier is None and self._cursor <= ob.acked:
                return
            await asyncio.sleep(0.002)

    def _publish_records(
        self, batch: list[tuple[int, bytes]] | list[tuple[int, PointUpdate]], link: MqttLink
    ) -> None:
        """DDATA for ``batch`` (seq order), consecutive records of one device in one
        message; records of a dead device or no point passed by."""
        group: list[tuple[MetricDef, LatestValue]] = []
        device: DeviceDef | None = None
        for seq, rec in batch:
            self._cursor = seq
            try:
                update = rec if isinstance(rec, PointUpdate) else decode_update(rec)
            except UpdateError as e:  # an earlier pyrtu's JSON mode's record
                if not self.counts["foreign_records"]:
                    log.error("sparkplug: outbox record %d is no point update (%s): passed by "
                              "(a backlog of an earlier pyrtu's JSON mode?); the others are "
                              "counted in foreign_records", seq, e)  # fmt: skip
                self.counts["foreign_records"] += 1
                continue
            found = self.session.metric.get(update.point)
            if found is None or found[0].id not in self._dborn:
                self.counts["unforwarded"] += 1
                continue
            dev, md = found
            if device is not None and (dev is not device or len(group) >= _PER_MESSAGE):
                self._send_ddata(link, device, group)
                group = []
            device = dev
            historical = seq < self._live_from
            group.append((md, LatestValue(update.value, update.time, update.quality, historical)))
        if device is not None and group:
            self._send_ddata(link, device, group)
        link.write_now()

    def _send_ddata(
        self, link: MqttLink, device: DeviceDef, group: list[tuple[MetricDef, LatestValue]]
    ) -> None:
        body = self.session.ddata(group, time.time())
        link.publish(self.session.topic("DDATA", device), body, 0, False)
        self.counts["ddata"] += 1
        for _, s in group:
            self.counts["metrics_historical" if s.historical else "metrics_live"] += 1

    def _births(self, link: MqttLink) -> None:
        """NBIRTH and a DBIRTH for every device alive; what waits in the outbox is
        historical from now on."""
        ob = self._outbox
        assert ob is not None
        self._flush_live()
        self._live_from = ob.next_seq
        link.publish(self.session.nbirth_topic, self.session.nbirth(time.time()), 0, False)
        self.counts["nbirth"] += 1
        self._born = True
        self._dborn.clear()
        for dev in self.spb.devices:
            if dev.id in self._alive:
                self._publish_dbirth(dev)
        link.write_now()
        if self._pump_soon is not None:
            self._pump_soon.cancel()
        self._pump()

    def _publish_dbirth(self, dev: DeviceDef) -> None:
        link = self._link
        if link is None or not link.connected:
            return
        samples = {
            m.point.name: self._latest[m.point.name]
            for m in dev.metrics
            if m.point.name in self._latest
        }
        link.publish(
            self.session.topic("DBIRTH", dev),
            self.session.dbirth(dev, samples, time.time()),
            0,
            False,
        )
        link.write_now()
        self._dborn.add(dev.id)
        self.counts["dbirth"] += 1

    def _say_death(self, link: MqttLink) -> None:
        """The NDEATH published by the node itself (an intentional disconnect)."""
        self._flush_live()
        body = self.session.ndeath(self.session.bdseq, time.time())
        link.publish(self.session.ndeath_topic, body, 1, False)
        link.write_now()
        self._born = False
        self._dborn.clear()

    # ------------------------------------------------------------------ commands and STATE

    def _on_message(self, msg: paho.MQTTMessage) -> None:
        # handled after paho's read returns: a birth writes to the socket at once,
        # and paho's write must not run inside its own message callback
        asyncio.get_running_loop().call_soon(self._handle, msg.topic, bytes(msg.payload))

    def _handle(self, topic: str, payload: bytes) -> None:
        if topic == self.session.state_topic:
            self._on_state(payload)
        elif topic == self.session.ncmd_topic:
            self._on_ncmd(payload)
        elif topic.startswith(self.session.dcmd_filter[:-1]):
            self._on_dcmd(topic.rsplit("/", 1)[1], payload)

    def _on_state(self, payload: bytes) -> None:
        online = self.host.update(payload)
        link = self._link
        if online is None or link is None or not link.connected:
            if online is None:
                log.warning("sparkplug: a STATE of %s ignored (not STATE JSON, or older "
                            "than the last one)", self.spb.primary_host_id)  # fmt: skip
            return
        if online and not self._born:
            log.info("sparkplug: primary host %s online", self.spb.primary_host_id)
            self._births(link)
        elif not online and self._born:
            log.warning("sparkplug: primary host %s offline: NDEATH, disconnecting",
                        self.spb.primary_host_id)  # fmt: skip
            self.counts["host_offline"] += 1
            self._say_death(link)
            link.close(graceful=True, with_will=True)
            self._on_lost("primary host offline")

    def _decode(self, payload: bytes, what: str) -> Any | None:
        try:
            return payload_class().FromString(payload)
        except Exception as e:  # protobuf's DecodeError: not a Sparkplug payload
            self._refuse("malformed", f"{what}: not a Sparkplug B payload ({e})")
            return None

    def _on_ncmd(self, payload: bytes) -> None:
        p = self._decode(payload, "NCMD")
        if p is None:
            return
        for m in p.metrics:
            if m.name == NODE_REBIRTH:  # it has no alias (rebirth-name-aliases)
                if m.WhichOneof("value") == "boolean_value" and m.boolean_value:
                    self._rebirth()
                else:
                    self._refuse("validation", "NCMD Node Control/Rebirth takes boolean true")
            else:
                self._refuse("unknown_metric", f"NCMD: no node metric {m.name or m.alias!r}")

    def _rebirth(self) -> None:
        link = self._link
        if (
            link is None
            or not link.connected
            or (self.spb.primary_host_id and not self.host.online)
        ):
            return
        self.counts["rebirths"] += 1
        log.info("sparkplug: rebirth requested")
        self._births(link)

    def _on_dcmd(self, device_id: str, payload: bytes) -> None:
        dev = self.session.device.get(device_id)
        if dev is None:
            self._refuse("unknown_device", f"DCMD for no device of this node: {device_id!r}")
            return
        p = self._decode(payload, f"DCMD {device_id}")
        if p is None:
            return
        by_name = {md.name: md for md in dev.metrics}
        by_alias = {md.alias: md for md in dev.metrics}
        for m in p.metrics:
            md = by_name.get(m.name) if m.name else by_alias.get(m.alias)
            if md is None:
                self._refuse("unknown_metric", f"DCMD {device_id}: no metric {m.name or m.alias!r}")
                continue
            try:
                value = get_value(m, md.datatype)
            except ValueError as e:
                self._refuse("validation", f"DCMD {device_id}/{md.name}: {e}")
                continue
            self.counts["dcmd"] += 1
            refusal = self.writer.command(md.point.name, value, f"DCMD {device_id}/{md.name}")
            if refusal is not None:
                self.dcmd_refused[refusal.error] = self.dcmd_refused.get(refusal.error, 0) + 1

    def _refuse(self, reason: str, message: str) -> None:
        self.dcmd_refused[reason] = self.dcmd_refused.get(reason, 0) + 1
        log.warning("sparkplug: command refused (%s): %s", reason, message)

    # ------------------------------------------------------------------ the connection

    def _new_link(self) -> MqttLink:
        """A link whose will is the NDEATH of a new bdSeq (one per CONNECT sent)."""
        bdseq = self._bdseq.take()
        self.session.bdseq = bdseq
        return MqttLink(
            self.config.mqtt,
            self.session.ndeath_topic,
            on_message=self._on_message,
            on_ack=lambda mid: None,
            on_lost=self._on_lost,
            credentials=self._credentials,
            will=(self.session.ndeath(bdseq, time.time()), False),
        )

    def _fatal(self, e: BaseException) -> None:
        log.error("sparkplug: %s", e)
        self._halt(e)

    def _unreachable(self, e: BaseException) -> None:
        log.warning("sparkplug: broker %s unreachable: %s (retrying)", self.config.mqtt.broker, e)

    def _connected_to(self, link: MqttLink, outage: Outage | None) -> None:
        self.counts["connects"] += 1
        self.writer.connected(link)
        subs = [self.session.ncmd_topic, self.session.dcmd_filter]
        if self.session.state_topic is not None:
            subs.append(self.session.state_topic)
        link.subscribe(subs)
        if self.session.state_topic is None:
            self._births(link)
        # else the retained STATE (subscribed above) says whether the host is online

    def _broker_lost(self) -> None:
        log.warning("sparkplug: lost the broker %s (retrying)", self.config.mqtt.broker)

    def _link_gone(self) -> None:
        link, self._link = self._link, None
        if link is not None and link.connected:
            link.close(graceful=False)
        # what the broker did not confirm is published again after the next births
        # (historical: older than the values they carry)
        self._barrier = None
        self._live = []
        if self._outbox is not None:
            self._cursor = self._outbox.acked
        self._born = False
        self._dborn.clear()
        self.host.online = False

    # ------------------------------------------------------------------ figures

    def stats(self) -> dict[str, Any]:
        """The node's figures (JSON-ready; no secret in them)."""
        ob = self._outbox
        oldest = ob.oldest_time if ob is not None else None
        return {
            "group_id": self.spb.group_id,
            "edge_node_id": self.spb.edge_node_id,
            "connected": self._connected(),
            "born": self._born,
            "bdseq": self.session.bdseq,
            "devices_alive": sorted(self._alive),
            "outbox_depth": ob.depth if ob is not None else 0,
            "outbox_bytes": ob.bytes_used if ob is not None else 0,
            "oldest_unsent_s": (
                None if oldest is None else round(max(0.0, time.monotonic() - oldest), 3)
            ),
            "outbox_dropped": ob.dropped if ob is not None else 0,
            "outages": self._reconnect.outages,
            **self.counts,
            "dcmd_refused": dict(self.dcmd_refused),
            "commands": self.writer.stats(),
        }

    def health(self) -> list[str]:
        """What keeps the node from doing its work, one line each (empty: it polls,
        its tasks run, the outbox is open, the broker connected and the node born):
        the poller's problems (`Poller.health`), a fatal error, the outbox closed, a
        task not running, the broker not connected, the primary host offline (the
        node publishes nothing until it is back).  No secret in the lines: the
        broker's URL has none."""
        problems = self._problems("edge node", True)
        if self._running and self._connected() and not self._born and self.spb.primary_host_id:
            problems.append(
                f"primary host {self.spb.primary_host_id} offline: the node waits to be born"
            )
        return problems


__all__ = ["EdgeNode"]
