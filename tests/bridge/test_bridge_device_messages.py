"""``messages = "device"``: the JSON bridge's values in one message per device per
poll, ``{prefix}/{edge}/{bus}/{slave}/values``, ``{"points": {NAME: PAYLOAD}}``
where each PAYLOAD is the point's own payload (value, time, quality, seq, and
historical), not retained.  Through a real mosquitto: a previous run's backlog
grouped per slave and poll, a point never twice in a message, the records that
can never be published set aside between messages, an earlier pyrtu's records
published as they were; live values, acknowledgements, an outage's backlog and
stale values; a message the broker refuses sets aside every record it carries;
twenty Modbus TCP devices whose every step of every register arrives once, in
order; configuration errors at their line, exit 2, before anything connects.
Every expected payload here is written out by hand, not made by pyrtu."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cli_helpers import Background, pyrtu
from mqtt_broker import Broker, Client, Gate
from test_bridge_many_changes import DEVICES, REGISTERS, STEP, bridge_text, simulated
from waiting import wait_for

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge, BridgeEvent
from pyrtu.bridge.delivery import DeliveryWindow
from pyrtu.drivers.aio import run as aio_run
from pyrtu.outbox.outbox import Outbox
from pyrtu.outbox.updates import PointUpdate, decode_update, encode_update
from pyrtu.poller import SlaveState, Update

#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0
T0 = 1700000000.0  # the read times below: T0 + k / 4, exact binary fractions


def config(url: str, outbox: Path, more: str = "") -> str:
    """Points p0, p1 of slave 1, q0 of slave 2 and r0 of slave 3 on the bus "bus";
    device messages."""
    points = "".join(
        f'[[point]]\nname = "{name}"\nbus = "bus"\nslave = {slave}\ntable = "holding"\n'
        f"address = {address}\n"
        for name, slave, address in (("p0", 1, 0), ("p1", 1, 1), ("q0", 2, 0), ("r0", 3, 0))
    )
    return (
        f'[mqtt]\nurl = "{url}"\nedge = "e1"\noutbox = "{outbox}"\nqos = 1\n'
        'messages = "device"\nstats_interval = 3600\nbackoff = 0.1\nmax_backoff = 0.2\n'
        f'{more}[[bus]]\nname = "bus"\nport = "/dev/null"\nbaudrate = 19200\n' + points
    )


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def values(sub: Client) -> list[tuple[str, bytes, bool]]:
    """(topic, payload, retained) of what ``sub`` received, but the statuses and stats."""
    return [
        (t, p, r) for t, p, r, *_ in list(sub.messages) if not t.endswith(("/status", "/stats"))
    ]


def entry(value: object, k: float, quality: str, seq: int, hist: bool = False) -> dict[str, Any]:
    doc: dict[str, Any] = {"value": value, "time": T0 + k / 4, "quality": quality, "seq": seq}
    if hist:
        doc["historical"] = True
    return doc


def upd(name: str, value: object, k: float, quality: str = "good") -> bytes:
    return encode_update(PointUpdate(name, value, T0 + k / 4, quality))  # type: ignore[arg-type]


#: a previous run's backlog: seq n is the n-th record
OLD = [
    upd("p0", 1, 1),  # 1 \ one poll of slave 1
    upd("p1", 2, 1),  # 2 /
    upd("q0", 3, 2, "stale"),  # 3: slave 2 went silent
    upd("p0", 4, 3),  # 4 \ the next poll of slave 1
    upd("p1", None, 3, "bad"),  # 5 /
    upd("gone", 6, 4),  # 6: a point this configuration lacks: set aside
    upd("p0", 7, 5),  # 7
    b'pyrtu/e1/bus/1/p1\n{"value":8,"time":1700000001.5,"quality":"good"',  # 8: v1 record
    upd("p0", 9, 6),  # 9
    upd("p0", 10, 7),  # 10: p0 twice: a message of its own
    b"\x00pu1[damaged",  # 11: set aside
    upd("q0", 12, 8),  # 12
]


class OrderedWindow(DeliveryWindow):
    """The bridge's window, recording the seq each publication or record passed by
    stands at: the outbox's order, or an acknowledgement could commit a record of a
    message still awaiting its own."""

    def __init__(self, window: int) -> None:
        super().__init__(window)
        self.order: list[int] = []

    def sent_group(self, mid: int, read_at: float, records: list[tuple[int, bytes]]) -> None:
        self.order.append(records[-1][0])
        super().sent_group(mid, read_at, records)

    def skipped(self, seq: int) -> bool:
        self.order.append(seq)
        return super().skipped(seq)


def test_a_previous_runs_backlog_in_device_messages(tmp_path: Path) -> None:
    directory = tmp_path / "ob"
    with Outbox(directory) as ob:
        assert [ob.append(r, 1.0) for r in OLD] == list(range(1, 13))
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(config(broker.url, directory), "b.toml")
        sub = Client(broker, ["pyrtu/e1/#"])
        events: list[BridgeEvent] = []

        window = OrderedWindow(cfg.mqtt.inflight)

        async def main() -> dict[str, Any]:
            bridge = Bridge(cfg)
            bridge._window = window
            bridge.on_event(events.append)
            await bridge.start(poll=False)
            try:
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the outbox acked")
                await until(lambda: len(values(sub)) >= 7, "every message")
                return bridge.stats()
            finally:
                await bridge.stop()

        stats = aio_run(main())
        sub.close()
        # a late subscriber: the earlier pyrtu's record was retained, as it was; no
        # device message is
        with Client(broker, ["pyrtu/e1/#"]) as late:
            late.wait(lambda: len(values(late)) >= 1, "the retained value")
            time.sleep(0.2)
            assert [(t, r) for t, _, r in values(late)] == [("pyrtu/e1/bus/1/p1", True)]
    got = values(sub)
    dev1, dev2 = "pyrtu/e1/bus/1/values", "pyrtu/e1/bus/2/values"
    want = [
        (dev1, {"p0": entry(1, 1, "good", 1, True), "p1": entry(2, 1, "good", 2, True)}),
        (dev2, {"q0": entry(3, 2, "stale", 3, True)}),
        (dev1, {"p0": entry(4, 3, "good", 4, True), "p1": entry(None, 3, "bad", 5, True)}),
        (dev1, {"p0": entry(7, 5, "good", 7, True)}),
        ("pyrtu/e1/bus/1/p1", entry(8, 6, "good", 8, True)),  # as the earlier pyrtu did
        (dev1, {"p0": entry(9, 6, "good", 9, True)}),
        (dev1, {"p0": entry(10, 7, "good", 10, True)}),
        (dev2, {"q0": entry(12, 8, "good", 12, True)}),
    ]
    assert [(t, json.loads(p)["points"] if t.endswith("/values") else json.loads(p))
            for t, p, _ in got] == want  # fmt: skip
    # the bytes: the points in sequence order, each its point payload
    assert got[0][1] == (
        b'{"points":{"p0":{"value":1,"time":1700000000.25,"quality":"good","seq":1,'
        b'"historical":true},"p1":{"value":2,"time":1700000000.25,"quality":"good",'
        b'"seq":2,"historical":true}}}'
    )
    assert stats["quarantined"] == 2 and stats["drops"] == 0
    # each message at its last record, each record set aside in its place
    assert window.order == [2, 3, 5, 6, 7, 8, 9, 10, 11, 12]
    lines = [json.loads(x) for x in (directory / "quarantine.jsonl").read_text().splitlines()]
    assert [x["seq"] for x in lines] == [6, 11]
    assert decode_update(lines[0]["record"].encode()) == PointUpdate("gone", 6, T0 + 1, "good")
    with Outbox(directory) as ob:  # every record acknowledged or set aside
        assert ob.depth == 0 and ob.pending(100) == []


def test_live_values_acks_an_outage_and_stale(tmp_path: Path) -> None:
    """A poll of each slave is one message each, live; acknowledged, the outbox
    empties; the broker goes away: three polls of slave 1 and slave 2 going
    silent (its point stale, with its last value and time) wait in the outbox and
    arrive once, in order, historical, when it is back (and nothing else: slave
    3's value, acknowledged before, is not published again); then live again."""
    with Broker(tmp_path) as broker, Gate(broker) as gate:
        cfg = parse_bridge_config(config(gate.url, tmp_path / "ob"), "b.toml")
        pts = {p.name: p for p in cfg.poller.points}
        subs = [Client(broker, ["pyrtu/e1/#"])]

        def poll(values: dict[str, int], k: float) -> list[Update]:
            return [Update(pts[n], v, T0 + k / 4) for n, v in values.items()]

        async def main() -> tuple[dict[str, Any], dict[str, Any]]:
            bridge = Bridge(cfg)
            await bridge.start(poll=False)
            try:
                await until(lambda: bridge.stats()["connected"], "connected")
                for u in poll({"p0": 10, "p1": 11}, 1) + poll({"q0": 12}, 1) + poll({"r0": 13}, 1):
                    bridge.feed(u)
                await until(lambda: bridge.stats()["acknowledged"] == 4, "four acknowledged")
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the outbox acked")
                acked = bridge.stats()
                gate.close()
                await asyncio.to_thread(broker.kill)
                subs[0].close()
                await until(lambda: not bridge.stats()["connected"], "the connection lost")
                for k, base in ((2, 20), (3, 30), (4, 40)):
                    for u in poll({"p0": base, "p1": base + 1}, k):
                        bridge.feed(u)
                bridge.feed(SlaveState("bus", 2, False, T0 + 5 / 4))
                assert bridge.stats()["outbox_depth"] == 7
                await asyncio.to_thread(broker.start)
                subs.append(await asyncio.to_thread(Client, broker, ["pyrtu/e1/#"]))
                await asyncio.to_thread(gate.open)
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the backlog acked")
                for u in poll({"p0": 50}, 6):
                    bridge.feed(u)
                await until(lambda: len(values(subs[1])) == 5, "the live value after")
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "all acked")
                return acked, bridge.stats()
            finally:
                await bridge.stop()

        acked, stats = aio_run(main())
        subs[1].close()
    dev1, dev2 = "pyrtu/e1/bus/1/values", "pyrtu/e1/bus/2/values"
    before = [(t, json.loads(p)["points"], r) for t, p, r in values(subs[0])]
    assert before == [
        (dev1, {"p0": entry(10, 1, "good", 1), "p1": entry(11, 1, "good", 2)}, False),
        (dev2, {"q0": entry(12, 1, "good", 3)}, False),
        ("pyrtu/e1/bus/3/values", {"r0": entry(13, 1, "good", 4)}, False),
    ]
    assert acked["published"] == acked["acknowledged"] == acked["updates"] == 4
    after = [(t, json.loads(p)["points"], r) for t, p, r in values(subs[1])]
    assert after == [
        (dev1, {"p0": entry(20, 2, "good", 5, True), "p1": entry(21, 2, "good", 6, True)}, False),
        (dev1, {"p0": entry(30, 3, "good", 7, True), "p1": entry(31, 3, "good", 8, True)}, False),
        (dev1, {"p0": entry(40, 4, "good", 9, True), "p1": entry(41, 4, "good", 10, True)}, False),
        # stale: the last value read, when it was read
        (dev2, {"q0": entry(12, 1, "stale", 11, True)}, False),
        (dev1, {"p0": entry(50, 6, "good", 12)}, False),
    ]
    assert stats["published"] == stats["acknowledged"] == stats["updates"] == 12
    assert stats["drops"] == 0 and stats["quarantined"] == 0


def test_a_device_message_the_broker_refuses_sets_aside_every_record_it_carries(
    tmp_path: Path,
) -> None:
    """mosquitto denies slave 1's messages by ACL (PUBACK 0x87): both records of
    its message are set aside, not counted delivered; slave 2's arrive."""
    broker = Broker(tmp_path)
    acl = tmp_path / "acl"
    acl.write_text("topic readwrite pyrtu/#\ntopic deny pyrtu/e1/bus/1/values\n")
    broker.conf.write_text(broker.conf.read_text() + f"acl_file {acl}\n")
    directory = tmp_path / "ob"
    with broker:
        cfg = parse_bridge_config(config(broker.url, directory), "b.toml")
        pts = {p.name: p for p in cfg.poller.points}
        sub = Client(broker, ["pyrtu/e1/#"])
        events: list[BridgeEvent] = []

        async def main() -> dict[str, Any]:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            await bridge.start(poll=False)
            try:
                await until(lambda: bridge.stats()["connected"], "connected")
                for name, v in (("q0", 1), ("p0", 2), ("p1", 3), ("q0", 4)):
                    bridge.feed(Update(pts[name], v, T0))
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the outbox acked")
                return bridge.stats()
            finally:
                await bridge.stop()

        stats = aio_run(main())
        sub.wait(lambda: len(values(sub)) == 2, "slave 2's messages")
        sub.close()
    assert [(t, json.loads(p)["points"]["q0"]["value"]) for t, p, _ in values(sub)] == [
        ("pyrtu/e1/bus/2/values", 1),
        ("pyrtu/e1/bus/2/values", 4),
    ]
    assert stats["quarantined"] == 2
    lines = [json.loads(x) for x in (directory / "quarantine.jsonl").read_text().splitlines()]
    assert [(x["seq"], decode_update(x["record"].encode()).point) for x in lines] == [
        (2, "p0"),
        (3, "p1"),
    ]
    assert all("0x87" in x["reason"] for x in lines)
    # reported once, by the topic the broker refused
    assert [(e.detail["seq"], e.detail["topic"]) for e in events if e.kind == "quarantined"] == [
        (2, "pyrtu/e1/bus/1/values")
    ]


def test_a_device_message_is_acknowledged_for_every_record_it_carries() -> None:
    """The window: a message stands at its last record; an acknowledgement of a
    later message commits nothing while an earlier one awaits its own."""
    w = DeliveryWindow(2)
    w.sent_group(1, 100.0, [(1, b"a"), (2, b"b")])
    w.sent_group(2, 100.0, [(3, b"c")])
    assert w.full and w.records(1) == [(1, b"a"), (2, b"b")]
    assert not w.acked(2, 101.0) and w.contiguous is None
    assert w.acked(1, 101.0) and w.contiguous == 3
    assert w.records(1) == [] and len(w) == 0 and w.published == w.acknowledged == 3
    w.sent_group(3, 0.0, [(4, b"d"), (6, b"f")])
    assert w.acked(3, 102.0) and w.contiguous == 6
    w.sent_group(4, 0.0, [(8, b"h")])
    assert w.skipped(9) is False and w.contiguous == 6  # behind the message
    assert w.acked(4, 102.0) and w.contiguous == 9


def test_configuration_errors_exit_2_at_their_line_before_anything_connects(
    tmp_path: Path,
) -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.5)
    url = f"mqtt://127.0.0.1:{listener.getsockname()[1]}"
    values_point = '[[point]]\nname = "values"\nbus = "bus"\nslave = 1\ntable = "holding"\n'
    cases = [
        # (the configuration, the line of messages, the message)
        (config(url, tmp_path / "ob").replace('"device"', '"devices"'), 6,
         "mqtt: messages: must be 'point' or 'device', not 'devices'"),
        (config(url, tmp_path / "ob").replace('"device"', "1"), 6,
         "mqtt: messages: must be 'point' or 'device', not 1"),
        (config(url, tmp_path / "ob") + values_point + "address = 7\n", 6,
         "mqtt: messages: the device messages of slave 1 on bus: topic "
         "'pyrtu/e1/bus/1/values' is also point 'values' (rename that point, or give "
         "it a topic of its own)"),
        (config(url, tmp_path / "ob") + '[[point]]\nname = "x"\nbus = "bus"\nslave = 2\n'
         'table = "holding"\naddress = 9\ntopic = "pyrtu/e1/bus/2/values"\n', 6,
         "topic 'pyrtu/e1/bus/2/values' is also point 'x'"),
        (config(url, tmp_path / "ob", "discovery = true\n"), 6,
         "mqtt: messages: 'device' with discovery: Home Assistant reads each point's"),
        (config(url, tmp_path / "ob") + '[sparkplug]\ngroup_id = "g"\n', 6,
         "mqtt: messages: 'device' is the JSON bridge's; a [sparkplug] edge node"),
    ]  # fmt: skip
    try:
        for n, (text, line, message) in enumerate(cases):
            path = tmp_path / f"b{n}.toml"
            path.write_text(text)
            assert text.splitlines()[line - 1].startswith("messages = ")
            for mode in ("--check", "--config"):
                r = pyrtu("bridge", mode, path)
                assert r.code == 2, (n, r.err)
                assert f"b{n}.toml:{line}: " in r.err and message in r.err, (n, r.err)
                assert "Traceback" not in r.err
        try:
            listener.accept()[0].close()
            raise AssertionError("the bridge connected to the broker")
        except TimeoutError:
            pass
        # the same point named "values" with a message per point: a valid configuration
        path = tmp_path / "point.toml"
        path.write_text(cases[2][0].replace('messages = "device"', 'messages = "point"'))
        r = pyrtu("bridge", "--check", path)
        assert r.code == 0, r.err
    finally:
        listener.close()


def test_every_step_of_every_register_arrives_once_in_order_in_device_messages(
    tmp_path: Path,
) -> None:
    """Twenty simulated Modbus TCP devices of thirty registers stepping every half
    second, polled five times a step: every step of every register arrives once,
    in order, in its device's messages, most of them a poll's thirty changes."""
    with simulated(tmp_path) as first:
        with Broker(tmp_path) as broker, Client(broker, ["pyrtu/many/#"]) as sub:
            config_path = tmp_path / "bridge.toml"
            config_path.write_text(bridge_text(broker.url, tmp_path / "outbox", first, "device"))
            bridge = Background("bridge", "--config", config_path)
            try:

                def seen() -> set[str]:
                    names: set[str] = set()
                    for _t, body, *_ in values(sub):
                        names.update(json.loads(body)["points"])
                    return names

                def started() -> bool:
                    assert bridge.proc.poll() is None, "".join(bridge.err)
                    return len(seen()) == DEVICES * REGISTERS

                sub.wait(started, "a value of every point", 60)
                time.sleep(8 * STEP)
                bridge.proc.send_signal(signal.SIGTERM)
                assert bridge.finish(30).code == 0
            finally:
                bridge.kill()
            received = list(sub.messages)
    per_point: dict[str, list[tuple[int, float, int]]] = {}
    seqs: list[int] = []
    sizes: list[int] = []
    for topic, body, retained, _props, arrived in received:
        if topic.endswith(("/status", "/stats")):
            continue
        assert not retained, topic
        i = topic.split("/")[2][1:]
        assert topic == f"pyrtu/many/d{i}/1/values", topic
        points = json.loads(body)["points"]
        sizes.append(len(points))
        for name, doc in points.items():
            assert name.startswith(f"d{i}.r"), (topic, name)  # its own device's only
            assert set(doc) == {"value", "time", "quality", "seq"}, doc
            assert doc["quality"] == "good" and isinstance(doc["value"], int), doc
            assert isinstance(doc["time"], float) and doc["time"] <= arrived + 0.001, doc
            per_point.setdefault(name, []).append((doc["value"], doc["time"], doc["seq"]))
            seqs.append(doc["seq"])
    # every number once, in the order published (one connection, QoS 1)
    assert seqs == sorted(set(seqs)), "a sequence number out of order or twice"
    assert len(per_point) == DEVICES * REGISTERS
    for name, got in per_point.items():
        counts = [v for v, _, _ in got]
        # one step a value: consecutive counts (no change left out, none twice)
        assert counts == list(range(counts[0], counts[0] + len(counts))), (name, counts)
        assert len(counts) >= 7, (name, counts)
        r = int(name.partition(".r")[2])
        assert counts[0] >= r * 100, (name, counts)  # the ramp from its initial value
        times = [t for _, t, _ in got]
        assert times == sorted(times) and times[-1] - times[0] >= (len(times) - 2) * STEP * 0.8
    # a poll's changes in one message: almost every message holds the device's 30
    assert sum(s == REGISTERS for s in sizes) >= 0.9 * len(sizes), sizes


def test_a_set_command_with_device_messages(tmp_path: Path) -> None:
    """A set command goes to the point's set topic as in the default form; its
    result too; the value read back comes in the slave's device message, and
    nothing on the point's own topic."""
    from test_bridge_writes import BASE, BAUD, ref, vbus
    from test_bridge_writes import config as writes_config

    from pyrtu.devices import CFW701Simulator
    from pyrtu.drivers._loopthread import LoopThread

    with Broker(tmp_path) as broker, vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        try:
            text = writes_config(broker.url, bus.paths[0], tmp_path / "ob", 'messages = "device"')
            bridge = Bridge(parse_bridge_config(text, "b.toml"))
            thread = LoopThread("bridge", bridge.start, bridge.stop)
            thread.start()
            try:
                with Client(broker, ["pyrtu/e1/#"]) as cl:

                    def refs() -> list[object]:
                        return [
                            json.loads(p)["points"]["weg.ref"]["value"]
                            for p in cl.on(f"{BASE}/values")
                            if b'"weg.ref"' in p
                        ]

                    cl.wait(lambda: bool(refs()), "the reference's first value")
                    cl.publish(f"{BASE}/weg.ref/set", b'{"value": 1000, "id": "a1"}')
                    cl.wait(lambda: bool(cl.on(f"{BASE}/weg.ref/set/result")), "the result")
                    (res,) = [json.loads(p) for p in cl.on(f"{BASE}/weg.ref/set/result")]
                    assert res == {"ok": True, "point": "weg.ref", "id": "a1", "value": 1000,
                                   "time": res["time"]}  # fmt: skip
                    assert ref(sim) == 1000
                    cl.wait(lambda: refs()[-1] == 1000, "the value read back")
                    assert cl.on(f"{BASE}/weg.ref") == []
            finally:
                thread.stop()
        finally:
            sim.close()
