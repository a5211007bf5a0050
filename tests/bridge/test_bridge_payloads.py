"""What a point's payload says, through a real mosquitto: ``historical`` only for
what waited through an outage (never for the values read at start-up, however
late the broker comes up); a point never read says so (value and time null),
never a time of 1970; a write's read-back that a poll already published is not
published a second time."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

from mqtt_broker import Broker, Client, free_port
from test_bridge_broker import POINTS, drives, toml, topic, until

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge, BridgeEvent
from pyrtu.drivers.aio import run as aio_run
from pyrtu.poller import Update

GHOST = "pyrtu/e1/line/7/ghost.level"  # slave 7: no drive answers at that address


def docs(sub: Client, t: str) -> list[dict[str, Any]]:
    return [json.loads(p) for p in sub.on(t)]


def test_values_read_before_a_late_broker_are_live_not_historical(tmp_path: Path) -> None:
    """The broker comes up after the first poll (and after failed connection
    attempts): the first values are the edge's current state, not history."""
    broker = Broker(tmp_path, port=free_port())  # not started yet
    with drives() as (bus, _sims):
        cfg = parse_bridge_config(toml(broker.url, bus.paths[0], tmp_path / "ob"), "b.toml")
        events: list[BridgeEvent] = []
        sub: list[Client] = []

        async def main() -> None:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            async with bridge:
                await until(lambda: bridge.appended >= len(POINTS), "the first poll")
                await until(lambda: any(e.kind == "broker_down" for e in events), "a failure")
                await asyncio.to_thread(broker.start)
                sub.append(await asyncio.to_thread(Client, broker, ["pyrtu/e1/line/#"]))
                await until(lambda: all(sub[0].on(topic(n)) for n in POINTS), "every point")

        try:
            aio_run(main())
            for n in POINTS:
                got = docs(sub[0], topic(n))
                assert got and all("historical" not in d for d in got), (n, got)
        finally:
            for c in sub:
                c.close()
            broker.stop()


def test_historical_is_what_waited_through_an_outage(tmp_path: Path) -> None:
    """A previous run's backlog (the bridge itself was down) is historical; the
    values of this run published on its first connection are not; a value that
    waited through a lost connection is."""
    broker = Broker(tmp_path, port=free_port())
    cfg = parse_bridge_config(toml(broker.url, "/dev/null", tmp_path / "ob"), "b.toml")
    speed = next(p for p in cfg.poller.points if p.name == "weg.speed")
    t = topic("weg.speed")

    async def first_run() -> None:  # the broker down all along: 3 values kept
        bridge = Bridge(cfg)
        await bridge.start(poll=False)
        for v in (1, 2, 3):
            bridge.feed(Update(speed, v, time.time()))
        await bridge.stop(drain=0)

    async def second_run(sub: Client) -> list[dict[str, Any]]:
        bridge = Bridge(cfg)
        await bridge.start(poll=False)
        try:
            bridge.feed(Update(speed, 4, time.time()))  # read before the first connection
            await until(lambda: len(sub.on(t)) >= 4, "the backlog and the new value")
            bridge.feed(Update(speed, 5, time.time()))  # live
            await until(lambda: len(sub.on(t)) >= 5, "the live value")
            await asyncio.to_thread(broker.kill)  # the connection lost
            await until(lambda: not bridge.stats()["connected"], "the connection lost")
            bridge.feed(Update(speed, 6, time.time()))  # waits through the outage
            await asyncio.to_thread(broker.start)
            # the broker kept nothing: a new subscriber, the retained value
            late = await asyncio.to_thread(Client, broker, [t])
            try:
                await until(lambda: bool(late.on(t)), "the value after the outage")
                return docs(late, t)
            finally:
                late.close()
        finally:
            await bridge.stop()

    aio_run(first_run())
    broker.start()
    try:
        with Client(broker, ["pyrtu/e1/line/#"]) as sub:
            after = aio_run(second_run(sub))
            got = {d["value"]: d.get("historical", False) for d in docs(sub, t)[:5]}
        assert got == {1: True, 2: True, 3: True, 4: False, 5: False}, got
        assert [(d["value"], d.get("historical")) for d in after] == [(6, True)], after
    finally:
        broker.stop()


def test_a_point_never_read_is_published_with_value_and_time_null(tmp_path: Path) -> None:
    """Slave 7 never answers: the poller declares it offline and its point is
    published ``stale`` with value null and time null (never read), not 1970."""
    ghost = """
[[point]]
name = "ghost.level"
bus = "line"
slave = 7
table = "holding"
address = 0
"""
    with Broker(tmp_path) as broker, drives() as (bus, _sims):
        text = toml(broker.url, bus.paths[0], tmp_path / "ob") + ghost
        cfg = parse_bridge_config(text, "b.toml")
        with Client(broker, ["pyrtu/e1/line/#"]) as sub:

            async def main() -> None:
                async with Bridge(cfg):
                    await until(lambda: bool(sub.on(GHOST)), "the ghost's payload")
                    await until(lambda: all(sub.on(topic(n)) for n in POINTS), "the others")

            aio_run(main())
            (doc,) = docs(sub, GHOST)
            assert doc["value"] is None and doc["time"] is None and doc["quality"] == "stale"
            assert sub.on("pyrtu/e1/line/7/status")[-1:] == [b"offline"]


def test_a_read_back_a_poll_already_published_is_not_published_again(tmp_path: Path) -> None:
    """A poll between a write and its read-back reads the new value first: the
    read-back then publishes nothing (one publication per changed value); a
    read-back within the deadband, or a new value, is published."""
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(toml(broker.url, "/dev/null", tmp_path / "ob"), "b.toml")
        speed = next(p for p in cfg.poller.points if p.name == "weg.speed")
        t = topic("weg.speed")
        with Client(broker, ["pyrtu/e1/line/#"]) as sub:

            async def main() -> None:
                bridge = Bridge(cfg)
                await bridge.start(poll=False)
                try:
                    await until(lambda: bridge.stats()["connected"], "connected")
                    bridge.feed(Update(speed, 70, time.time()))  # the poll
                    bridge.publish_value(speed, 70, time.time())  # the read-back
                    bridge.publish_value(speed, 71, time.time())  # another value
                    # a duplicate of 70 would come before 71 (in sequence order)
                    await until(lambda: any(d["value"] == 71 for d in docs(sub, t)), "71")
                finally:
                    await bridge.stop()

            aio_run(main())
            got = [(d["value"], d["seq"]) for d in docs(sub, t)]
            assert [v for v, _ in got] == [70, 71], got
