"""The JSON bridge's records are point updates (#33.2); an outbox written by the
previous pyrtu (records of a topic and a payload) is delivered after an upgrade.

``tests/outbox/data/bridge-json-v1/`` (see its README) is an outbox the previous
bridge left (its broker unreachable), the configuration it ran with, and what that
same bridge published when it drained a copy of it into mosquitto
(``published.jsonl``).  The bridge of today drains the golden outbox into a real
mosquitto and must publish the same messages, byte for byte, in the same order;
the same values fed live must make the same payloads (but for ``historical``)."""

from __future__ import annotations

import asyncio
import json
import shutil
from pathlib import Path
from typing import Any

from mqtt_broker import Broker, Client
from waiting import wait_for

from pyrtu.bridge import BridgeConfig, parse_bridge_config
from pyrtu.bridge.bridge import Bridge
from pyrtu.drivers.aio import run as aio_run
from pyrtu.outbox.outbox import Outbox
from pyrtu.outbox.updates import PointUpdate, decode_update, encode_update, is_update
from pyrtu.poller import PointDropped, SlaveState, Update

GOLDEN = Path(__file__).parents[1] / "outbox" / "data" / "bridge-json-v1"
#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0
T = 1_800_000_000.0


def config(url: str, outbox: Path) -> BridgeConfig:
    text = (GOLDEN / "bridge.toml.in").read_text()
    text = text.replace("@URL@", url).replace("@OUTBOX@", str(outbox))
    return parse_bridge_config(text, "bridge.toml")


def golden_messages() -> list[tuple[str, bytes]]:
    """What the previous bridge published from the golden outbox, in order."""
    lines = (GOLDEN / "published.jsonl").read_text(encoding="utf-8").splitlines()
    return [(d["topic"], d["payload"].encode()) for d in map(json.loads, lines)]


def feed(bridge: Bridge) -> None:
    """The events the golden outbox was written with (its README)."""
    pts = {p.name: p for p in bridge.config.poller.points}
    bridge.feed(Update(pts["speed"], 1450, T + 0.125))
    bridge.feed(Update(pts["temp"], 5.099999904632568, T + 0.25))
    bridge.feed(Update(pts["level"], 21.400000000000002, T + 0.375))
    bridge.feed(Update(pts["running"], True, T + 0.5))
    bridge.feed(Update(pts["name"], 'pump "A" é', T + 0.625))
    bridge.feed(Update(pts["speed"], 1460, T + 1.125))
    bridge.feed(Update(pts["temp"], float("nan"), T + 1.25))
    bridge.feed(PointDropped(pts["level"], "illegal data address", T + 1.375))
    bridge.feed(SlaveState("line", 2, False, T + 2.0))
    bridge.feed(SlaveState("line", 1, False, T + 2.5))
    bridge.feed(Update(pts["speed"], -3, T + 3.125))


def points_published(sub: Client, cfg: BridgeConfig) -> list[tuple[str, bytes]]:
    from pyrtu.bridge.topics import Topics

    topics = set(Topics(cfg).point.values())
    return [(m[0], m[1]) for m in list(sub.messages) if m[0] in topics]


def drain(cfg: BridgeConfig, sub: Client, count: int) -> dict[str, Any]:
    async def main() -> dict[str, Any]:
        bridge = Bridge(cfg)
        await bridge.start(poll=False)
        try:
            await wait_for(lambda: bridge.stats()["outbox_depth"] == 0, "drained", PATIENCE)
            return bridge.stats()
        finally:
            await bridge.stop()

    stats = aio_run(main())
    sub.wait(lambda: len(points_published(sub, cfg)) >= count, f"{count} messages", PATIENCE)
    return stats


def test_the_golden_files_are_the_ones_written_once() -> None:
    """Their sha256 as tests/outbox/data/README.md gives them (never regenerated)."""
    import hashlib
    import re

    readme = (GOLDEN.parent / "README.md").read_text(encoding="utf-8")
    listed = dict(
        (name, digest)
        for digest, name in re.findall(r"^([0-9a-f]{64})  (bridge-json-v1/\S+)$", readme, re.M)
    )
    on_disk = {
        str(p.relative_to(GOLDEN.parent)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in GOLDEN.rglob("*")
        if p.is_file() and p.name != "bridge.toml.in"
    }
    assert on_disk == listed and len(listed) == 3


def test_the_golden_outbox_holds_records_of_the_previous_form(tmp_path: Path) -> None:
    shutil.copytree(GOLDEN / "outbox", tmp_path / "outbox")
    with Outbox(tmp_path / "outbox") as ob:
        records = ob.pending(100)
    assert [seq for seq, _ in records] == list(range(1, 15))
    assert not any(is_update(rec) for _, rec in records)
    assert all(rec.split(b"\n", 1)[0].decode() == t for (_, rec), (t, _) in
               zip(records, golden_messages(), strict=True))  # fmt: skip


def test_the_previous_versions_backlog_is_published_as_it_would_have_been(
    tmp_path: Path,
) -> None:
    directory = tmp_path / "outbox"
    shutil.copytree(GOLDEN / "outbox", directory)
    want = golden_messages()
    with Broker(tmp_path) as broker:
        cfg = config(broker.url, directory)
        sub = Client(broker, ["#"])
        stats = drain(cfg, sub, len(want))
        sub.close()
    assert points_published(sub, cfg) == want
    assert stats["quarantined"] == 0 and stats["acknowledged"] == len(want)
    with Outbox(directory) as ob:
        assert ob.depth == 0 and ob.next_seq == len(want) + 1


def test_a_backlog_of_both_forms_is_published_in_order(tmp_path: Path) -> None:
    """The previous version's records, then point updates the new bridge wrote
    behind them (the broker still away after the upgrade): one sequence, in order;
    each update's payload as the JSON mode writes it."""
    directory = tmp_path / "outbox"
    shutil.copytree(GOLDEN / "outbox", directory)
    with Outbox(directory) as ob:
        for update in (
            PointUpdate("speed", 1500, T + 10.5, "good"),
            PointUpdate("running", False, T + 11.0, "good"),
            PointUpdate("temp", 5.099999904632568, T + 11.5, "good"),  # float32
        ):
            ob.append(encode_update(update), 0.0)
        ob.flush()
    want = [
        *golden_messages(),
        ("pyrtu/edge1/line/1/speed",
         b'{"value":1500,"time":1800000010.5,"quality":"good","seq":15,"historical":true}'),
        ("plant/pump/running",
         b'{"value":false,"time":1800000011.0,"quality":"good","seq":16,"historical":true}'),
        ("pyrtu/edge1/line/1/temp",
         b'{"value":5.1,"time":1800000011.5,"quality":"good","seq":17,"historical":true}'),
    ]  # fmt: skip
    with Broker(tmp_path) as broker:
        cfg = config(broker.url, directory)
        sub = Client(broker, ["#"])
        stats = drain(cfg, sub, len(want))
        sub.close()
    assert points_published(sub, cfg) == want
    assert stats["quarantined"] == 0


def test_live_values_make_the_payloads_of_the_previous_version(tmp_path: Path) -> None:
    """The golden feed, live into a fresh outbox with the broker connected: each
    payload is the previous version's byte for byte, without ``historical``."""
    want = [(t, p.replace(b',"historical":true}', b"}")) for t, p in golden_messages()]
    with Broker(tmp_path) as broker:
        cfg = config(broker.url, tmp_path / "outbox")
        sub = Client(broker, ["#"])

        async def main() -> None:
            bridge = Bridge(cfg)
            await bridge.start(poll=False)
            try:
                await wait_for(lambda: bridge.stats()["connected"], "connected", PATIENCE)
                feed(bridge)
                await wait_for(lambda: bridge.stats()["outbox_depth"] == 0, "acked", PATIENCE)
            finally:
                await bridge.stop()
            await asyncio.sleep(0)

        aio_run(main())
        sub.wait(lambda: len(points_published(sub, cfg)) >= len(want), "the values", PATIENCE)
        sub.close()
    assert points_published(sub, cfg) == want


def test_the_bridge_stores_point_updates_not_topics(tmp_path: Path) -> None:
    """With the broker away, what the bridge appends is a point update per value:
    the point's name, never its topic nor a JSON payload."""
    cfg = config("mqtt://127.0.0.1:1", tmp_path / "outbox")  # nothing listens there

    async def main() -> None:
        bridge = Bridge(cfg)
        await bridge.start(poll=False)
        try:
            feed(bridge)
        finally:
            await bridge.stop(drain=0)

    aio_run(main())
    with Outbox(tmp_path / "outbox") as ob:
        records = [rec for _, rec in ob.pending(100)]
    assert [decode_update(rec) for rec in records][:3] == [
        PointUpdate("speed", 1450, T + 0.125, "good"),
        PointUpdate("temp", 5.099999904632568, T + 0.25, "good"),
        PointUpdate("level", 21.400000000000002, T + 0.375, "good"),
    ]
    assert len(records) == 14 and all(b"pyrtu/" not in rec for rec in records)
