"""A record that can never be published (#27.1): an outbox written by a run whose
configuration let a wildcard, a NUL or a control character into a topic.  The
bridge sets each one aside (``quarantine.jsonl`` in the outbox's directory),
counts it, reports it once, and delivers every record behind it to a real broker
(mosquitto); the next run finds nothing left of them."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from mqtt_broker import Broker, Client
from waiting import wait_for

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge, BridgeEvent
from pyrtu.bridge.delivery import DeliveryWindow
from pyrtu.bridge.topics import unpublishable
from pyrtu.drivers.aio import run as aio_run
from pyrtu.outbox.outbox import Outbox
from pyrtu.outbox.updates import PointUpdate, decode_update, encode_update

#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 20.0


def config(url: str, outbox: Path) -> str:
    """The configuration as fixed: three points with good names."""
    points = "".join(
        f'[[point]]\nname = "p{i}"\nbus = "bus"\nslave = 1\ntable = "holding"\naddress = {i}\n'
        for i in range(3)
    )
    return (
        f'[mqtt]\nurl = "{url}"\nedge = "e1"\noutbox = "{outbox}"\nqos = 1\n'
        "stats_interval = 3600\nbackoff = 0.1\nmax_backoff = 0.2\n"
        '[[bus]]\nname = "bus"\nport = "/dev/null"\nbaudrate = 19200\n' + points
    )


def rec(topic: bytes, value: int) -> bytes:
    """An outbox record as the bridge writes it: the topic, a newline, the payload
    without its sequence number and closing brace (pyrtu/bridge/topics.py)."""
    return topic + b'\n{"value":%d,"time":1700000000.5,"quality":"good"' % value


#: what an older run left: good records with bad ones between them
OLD = [
    rec(b"pyrtu/e1/bus/1/p0", 1),
    rec(b"pyrtu/e1/bus/1/a+b", 2),  # the client refuses a wildcard
    rec(b"pyrtu/e1/bus/1/p1", 3),
    rec(b"pyrtu/e1/bus/1/x#", 4),
    rec(b"pyrtu/e1/bus/1/a\x00b", 5),  # the broker would drop the connection
    rec(b"pyrtu/e1/bus/1/a+b", 6),  # the same topic again: counted, reported once
    rec(b"pyrtu/e1/bus/1/p2", 7),
]
BAD = {2, 4, 5, 6}


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def test_an_old_outbox_with_unpublishable_records_delivers_the_rest(tmp_path: Path) -> None:
    directory = tmp_path / "ob"
    with Outbox(directory) as ob:
        assert [ob.append(r, 1.0) for r in OLD] == list(range(1, len(OLD) + 1))
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(config(broker.url, directory), "b.toml")
        sub = Client(broker, ["pyrtu/e1/#"])
        events: list[BridgeEvent] = []

        async def main() -> dict[str, object]:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            await bridge.start(poll=False)
            try:
                await until(
                    lambda: all(sub.on(f"pyrtu/e1/bus/1/p{i}") for i in range(3)), "the good ones"
                )
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the outbox acked")
                return bridge.stats()
            finally:
                await bridge.stop()

        stats = aio_run(main())
        sub.close()
    got = {
        t: json.loads(p)
        for t, p, *_ in sub.messages
        if t.startswith("pyrtu/e1/bus/1/") and t != "pyrtu/e1/bus/1/status"
    }
    want = {1: "p0", 3: "p1", 7: "p2"}
    assert got == {
        f"pyrtu/e1/bus/1/{name}": {
            "value": seq,
            "time": 1700000000.5,
            "quality": "good",
            "seq": seq,
            "historical": True,
        }
        for seq, name in want.items()
    }
    assert stats["quarantined"] == len(BAD)
    assert stats["connections"] == 1  # nothing the broker would refuse was sent to it
    reported = [e.detail for e in events if e.kind == "quarantined"]
    assert [d["seq"] for d in reported] == [2, 4, 5]  # once per topic
    assert all(d["file"] == str(directory / "quarantine.jsonl") for d in reported)
    assert "wildcard '+'" in str(reported[0]["reason"])
    assert "U+0000" in str(reported[2]["reason"])
    lines = [json.loads(x) for x in (directory / "quarantine.jsonl").read_text().splitlines()]
    assert [x["seq"] for x in lines] == sorted(BAD)
    assert [x["record"].encode() for x in lines] == [OLD[s - 1] for s in sorted(BAD)]
    with Outbox(directory) as ob:  # the next run: nothing left to block it
        assert ob.depth == 0 and ob.pending(100) == []


def test_unpublishable_records() -> None:
    assert unpublishable(rec(b"pyrtu/e1/bus/1/p0", 1)) is None
    assert unpublishable(rec("plant/温度/ü".encode(), 1)) is None
    for bad in (
        rec(b"a+b", 1),
        rec(b"a/#", 1),
        rec(b"a/b\x01", 1),
        rec(b"a/b\x7f", 1),
        rec(b"a//b", 1),
        rec(b"", 1),
        rec(b"\xff\xfe", 1),
        b"no newline",
    ):
        assert unpublishable(bad) is not None, bad


def test_a_skipped_record_counts_as_acknowledged_in_its_place() -> None:
    win = DeliveryWindow(8)
    assert win.skipped(1) and win.contiguous == 1  # nothing before it: passed at once
    win.sent(2, 100, 0.0)
    assert not win.skipped(3) and win.contiguous == 1  # 2 is still in flight
    win.sent(4, 101, 0.0)
    assert win.acked(100, 1.0) and win.contiguous == 3  # 2 acked: 3 with it
    assert win.acked(101, 1.0) and win.contiguous == 4
    assert win.published == 2 and win.acknowledged == 2  # a skip is neither


def test_the_quarantine_survives_a_reopen_and_is_on_disk_before_the_ack(tmp_path: Path) -> None:
    directory = tmp_path / "ob"
    with Outbox(directory) as ob:
        for r in OLD[:3]:
            ob.append(r, 1.0)
        ob.flush()
        assert not ob.quarantine_path.exists()  # made by the first record set aside
        ob.quarantine(2, OLD[1], "a reason")
        assert ob.quarantined == 1 and ob.stats()["quarantined"] == 1
        ob.ack(3)
    with Outbox(directory) as ob:
        assert ob.depth == 0 and ob.quarantined == 0  # counted per run
        ob.quarantine(9, b"\xff\n{}", "another")  # not UTF-8: kept as base64
    lines = [json.loads(x) for x in (directory / "quarantine.jsonl").read_text().splitlines()]
    assert [(x["seq"], x["reason"]) for x in lines] == [(2, "a reason"), (9, "another")]
    assert lines[0]["record"].encode() == OLD[1]
    assert lines[1]["record_base64"] == "/wp7fQ=="


def test_a_publication_the_broker_refuses_is_set_aside_not_counted_delivered(
    tmp_path: Path,
) -> None:
    """mosquitto answers a PUBLISH its ACL denies with PUBACK 0x87 (not authorized,
    MQTT 5 3.4.2.1): the record is copied aside and reported, not forgotten as
    if delivered; the records around it are delivered."""
    from pyrtu.poller import Point, Update

    broker = Broker(tmp_path)
    acl = tmp_path / "acl"
    acl.write_text("topic readwrite pyrtu/#\ntopic deny pyrtu/e1/bus/1/p1\n")
    broker.conf.write_text(broker.conf.read_text() + f"acl_file {acl}\n")
    directory = tmp_path / "ob"
    with broker:
        cfg = parse_bridge_config(config(broker.url, directory), "b.toml")
        sub = Client(broker, ["pyrtu/e1/#"])
        events: list[BridgeEvent] = []
        points = [Point(f"p{i}", "bus", 1, "holding", i) for i in range(3)]

        async def main() -> dict[str, object]:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            await bridge.start(poll=False)
            try:
                await until(lambda: bridge.stats()["connected"], "connected")
                for i, p in enumerate(points):
                    bridge.feed(Update(p, 10 + i, 1700000000.5))
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the outbox acked")
                return bridge.stats()
            finally:
                await bridge.stop()

        stats = aio_run(main())
        sub.wait(lambda: sub.on("pyrtu/e1/bus/1/p2"), "p2")
        sub.close()
    assert [json.loads(p)["value"] for p in sub.on("pyrtu/e1/bus/1/p0")] == [10]
    assert sub.on("pyrtu/e1/bus/1/p1") == []
    assert stats["quarantined"] == 1
    (reported,) = [e.detail for e in events if e.kind == "quarantined"]
    assert reported["topic"] == "pyrtu/e1/bus/1/p1" and "0x87" in str(reported["reason"])
    (line,) = [json.loads(x) for x in (directory / "quarantine.jsonl").read_text().splitlines()]
    # the record as stored: the point update (its topic is made when it is published)
    assert decode_update(line["record"].encode()) == PointUpdate("p1", 11, 1700000000.5, "good")
    assert line["seq"] == reported["seq"]


def test_updates_of_points_this_configuration_lacks_are_set_aside(tmp_path: Path) -> None:
    """Point updates (#33.2) whose point the configuration no longer has (renamed
    since they were stored), and a damaged one: set aside with the reason, counted,
    reported once each; the updates around them are published with the topics of
    today's configuration."""
    directory = tmp_path / "ob"
    stored = [
        encode_update(PointUpdate("p0", 1, 1700000000.5, "good")),
        encode_update(PointUpdate("gone", 2, 1700000000.5, "good")),
        encode_update(PointUpdate("p1", 3, 1700000000.5, "stale")),
        b"\x00pu1[damaged",
        encode_update(PointUpdate("gone", 5, 1700000000.5, "good")),
        encode_update(PointUpdate("p2", None, None, "stale")),
    ]
    with Outbox(directory) as ob:
        for r in stored:
            ob.append(r, 1.0)
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(config(broker.url, directory), "b.toml")
        sub = Client(broker, ["pyrtu/e1/#"])
        events: list[BridgeEvent] = []

        async def main() -> dict[str, object]:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            await bridge.start(poll=False)
            try:
                await until(lambda: bridge.stats()["outbox_depth"] == 0, "the outbox acked")
                return bridge.stats()
            finally:
                await bridge.stop()

        stats = aio_run(main())
        sub.wait(lambda: sub.on("pyrtu/e1/bus/1/p2"), "p2")
        sub.close()
    got = {t: p for t, p, *_ in sub.messages if t.split("/")[-1] in ("p0", "p1", "p2")}
    assert got == {
        "pyrtu/e1/bus/1/p0": b'{"value":1,"time":1700000000.5,"quality":"good","seq":1,'
        b'"historical":true}',
        "pyrtu/e1/bus/1/p1": b'{"value":3,"time":1700000000.5,"quality":"stale","seq":3,'
        b'"historical":true}',
        "pyrtu/e1/bus/1/p2": b'{"value":null,"time":null,"quality":"stale","seq":6,'
        b'"historical":true}',
    }
    assert stats["quarantined"] == 3
    reported = [e.detail for e in events if e.kind == "quarantined"]
    assert [(d["seq"], d["topic"]) for d in reported] == [
        (2, "gone"),
        (4, "a damaged point update"),
    ]  # once per name
    assert "point 'gone' is not in this configuration" in str(reported[0]["reason"])
    lines = [json.loads(x) for x in (directory / "quarantine.jsonl").read_text().splitlines()]
    assert [x["seq"] for x in lines] == [2, 4, 5]
    assert [x["record"].encode() for x in lines] == [stored[1], stored[3], stored[4]]
