"""The bridge against a real mosquitto (started per test on a free loopback port)
and the simulated drives on the virtual bus: retained values with time, quality
and sequence number; edge and slave status with the last will; stale points when a
slave is unplugged; a broker killed (SIGKILL) and restarted: nothing lost, order
kept, the backlog flagged historical, every retained topic back; credentials and
certificates refused with a clear message."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bridge_configs import BAUD, OUTAGE, drives, mqtt_table, weg_on_line
from mqtt_broker import Broker, Client, Gate
from waiting import wait_for

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge, BridgeEvent
from pyrtu.bridge.mqtt import BrokerRefused
from pyrtu.devices import CFW701Simulator, CV100Simulator
from pyrtu.drivers.aio import run as aio_run

#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0


def toml(url: str, port: str, outbox: Path, mqtt: str = "", interval: float = 0.05) -> str:
    return f"""
{mqtt_table(url, outbox, mqtt)}
{weg_on_line(port, interval, OUTAGE)}[[device]]
bus = "line"
slave = 5
profile = "cv100"
name = "cv"
interval = {interval}
"""


POINTS = [
    "weg.status",
    "weg.speed",
    "weg.current",
    "weg.fault",
    "weg.alarm",
    "cv.status",
    "cv.speed",
    "cv.current",
    "cv.fault",
]


def topic(name: str) -> str:
    return f"pyrtu/e1/line/{1 if name.startswith('weg') else 5}/{name}"


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def last(sub: Client, t: str) -> dict[str, Any] | None:
    got = sub.on(t)
    return json.loads(got[-1]) if got else None


def seqs(sub: Client) -> list[int]:
    out = []
    for t, p, *_ in list(sub.messages):
        if t.startswith("pyrtu/e1/line/") and not t.endswith("/status"):
            out.append(json.loads(p)["seq"])
    return out


def test_values_status_stale_and_the_last_will(tmp_path: Path) -> None:
    with Broker(tmp_path) as broker, drives() as (bus, sims):
        cfg = parse_bridge_config(toml(broker.url, bus.paths[0], tmp_path / "ob"), "b.toml")
        sub = Client(broker, ["pyrtu/#"])
        events: list[BridgeEvent] = []

        async def main() -> None:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            async with bridge:
                await until(lambda: all(last(sub, topic(n)) for n in POINTS), "every point")
                await until(lambda: sub.on("pyrtu/e1/line/5/status") == [b"online"], "online")
                assert sub.on("pyrtu/e1/status") == [b"online"]
                bus.unplug(2)
                sims[1].close()
                await until(lambda: sub.on("pyrtu/e1/line/5/status")[-1:] == [b"offline"], "5 off")
                await until(
                    lambda: all(
                        last(sub, topic(n))["quality"] == "stale"  # type: ignore[index]
                        for n in POINTS
                        if n.startswith("cv")
                    ),
                    "stale",
                )
                path = bus.replug(2)
                sims[1] = CV100Simulator()
                sims[1].serve(path, 5, baudrate=BAUD, parity="N")
                await until(
                    lambda: all(
                        last(sub, topic(n))["quality"] == "good"  # type: ignore[index]
                        for n in POINTS
                    ),
                    "good again",
                )
                assert sub.on("pyrtu/e1/line/5/status")[-1] == b"online"

        aio_run(main())
        sub.wait(lambda: sub.on("pyrtu/e1/status")[-1:] == [b"offline"], "offline at the end")
        sub.close()
        # every value as the drive holds it, with the time it was read
        weg = last(sub, topic("weg.status"))
        assert weg is not None
        assert weg["value"] == CFW701Simulator().store.holding_registers.get(680)
        assert (
            set(weg) == {"value", "time", "quality", "seq"} and abs(weg["time"] - time.time()) < 600
        )
        s = seqs(sub)
        assert s == sorted(s) and len(set(s)) == len(s)  # one edge, in order, never twice
        stale = [
            json.loads(p)
            for t, p, *_ in sub.messages
            if t == topic("cv.speed") and json.loads(p)["quality"] == "stale"
        ]
        assert stale and stale[0]["value"] == 50.0  # the last value read, marked stale
        assert [e.kind for e in events].count("slave") >= 4
        # a newcomer sees every retained topic
        with Client(broker, ["pyrtu/#"]) as late:
            late.wait(lambda: all(late.on(topic(n)) for n in POINTS), "retained values")
            late.wait(lambda: late.on("pyrtu/e1/status") == [b"offline"], "retained status")
            assert all(m[2] for m in late.messages)  # retained


def test_a_broker_killed_and_restarted_loses_nothing(tmp_path: Path) -> None:
    """SIGKILL of the broker while values come at every read (max_age 0.001):
    the bridge goes on polling into the outbox, then publishes the backlog in order,
    flagged historical; the subscriber gets every sequence number (none missing,
    none twice after de-duplication) and every retained topic is back."""
    with Broker(tmp_path) as broker, drives() as (bus, _sims), Gate(broker) as gate:
        text = toml(gate.url, bus.paths[0], tmp_path / "ob", "max_age = 0.001\nqos = 1", 0.02)
        cfg = parse_bridge_config(text, "b.toml")
        subs = [Client(broker, ["pyrtu/e1/line/#"])]
        events: list[BridgeEvent] = []

        async def main() -> Bridge:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            async with bridge:
                await until(lambda: len(subs[0].messages) > 100, "values before")
                appended = bridge.appended
                gate.close()
                broker.kill()
                subs[0].close()
                await until(lambda: any(e.kind == "broker_down" for e in events), "down")
                await until(lambda: bridge.appended > appended + 200, "polling goes on")
                assert bridge.stats()["outbox_depth"] > 100
                broker.start()
                subs.append(Client(broker, ["pyrtu/e1/line/#"]))
                gate.open()
                await until(
                    lambda: any(e.kind == "broker_up" and e.detail["down_s"] for e in events), "up"
                )
                await until(lambda: bridge.stats()["outbox_depth"] < 50, "backlog drained")
                await until(lambda: len(subs[1].messages) > 400, "values after")
            return bridge

        bridge = aio_run(main())
        final = bridge.final_stats
        assert final["drops"] == 0 and final["outbox_depth"] == 0
        before, after = seqs(subs[0]), seqs(subs[1])
        subs[1].close()
        got = sorted(set(before) | set(after))
        # every number from the first received to the last, none missing
        assert got == list(range(got[0], got[-1] + 1))
        assert got[-1] >= final["updates"] - 1
        # order per point kept (after de-duplication), the backlog flagged historical
        per_point: dict[str, list[int]] = {}
        seen: set[int] = set()
        historical = 0
        for sub in subs:
            for t, p, *_ in sub.messages:
                if t.endswith("/status"):
                    continue
                doc = json.loads(p)
                historical += doc.get("historical", False)
                if doc["seq"] in seen:
                    continue
                seen.add(doc["seq"])
                per_point.setdefault(t, []).append(doc["seq"])
        assert historical > 100
        assert all(v == sorted(v) for v in per_point.values())
        with Client(broker, ["pyrtu/#"]) as late:
            late.wait(lambda: all(late.on(topic(n)) for n in POINTS), "every retained value")
            late.wait(lambda: len(late.on("pyrtu/e1/line/1/status")) == 1, "slave status")
            assert late.on("pyrtu/e1/line/5/status") == [b"online"]


async def run_until_acknowledged(text: str) -> Bridge:
    """A bridge of configuration ``text`` run until its 9 points are acknowledged by the
    broker or it gives up (``fatal``); stopped."""
    bridge = Bridge(parse_bridge_config(text, "b.toml"))
    await bridge.start()
    await until(
        lambda: bridge.fatal is not None or bridge.stats()["acknowledged"] >= 9,
        "every point acknowledged, or the end",
    )
    await bridge.stop()
    return bridge


def test_refused_credentials_name_the_broker_and_the_user(tmp_path: Path) -> None:
    with Broker(tmp_path, users={"edge": "right-pw"}) as broker, drives() as (bus, _sims):
        ok = toml(
            broker.url, bus.paths[0], tmp_path / "ob1", 'username = "edge"\npassword = "right-pw"'
        )
        bad = toml(
            broker.url, bus.paths[0], tmp_path / "ob2", 'username = "edge"\npassword = "wrong-pw"'
        )

        good = aio_run(run_until_acknowledged(ok))
        assert good.fatal is None
        assert "right-pw" not in json.dumps(good.final_stats) + repr(good.config)
        refused = aio_run(run_until_acknowledged(bad))
        assert isinstance(refused.fatal, BrokerRefused)
        msg = str(refused.fatal)
        assert broker.url.split("//")[1] in msg and "'edge'" in msg
        assert "wrong-pw" not in msg
        assert "not authorized" in msg.lower() or "bad user name or password" in msg.lower()


def test_tls_verifies_the_broker_and_refuses_what_does_not(tmp_path: Path) -> None:
    with Broker(tmp_path, tls=True) as broker, drives() as (bus, _sims):
        trusted = toml(broker.url, bus.paths[0], tmp_path / "ob1", f'ca = "{broker.ca}"')
        untrusted = toml(broker.url, bus.paths[0], tmp_path / "ob2")  # the system's CAs
        sub = Client(broker, ["pyrtu/#"])

        good = aio_run(run_until_acknowledged(trusted))
        assert good.fatal is None
        sub.wait(lambda: bool(sub.on(topic("weg.status"))), "a value over TLS")
        sub.close()
        refused = aio_run(run_until_acknowledged(untrusted))
        assert refused.fatal is not None
        assert "certificate does not verify" in str(refused.fatal)
        assert refused.stats()["published"] == 0  # never downgraded to plain text


def test_a_full_outbox_refuses_new_updates_and_keeps_what_it_accepted(tmp_path: Path) -> None:
    """The broker unreachable and an outbox of 64 KiB with policy "refuse" (as a disk
    that fills): new updates are refused, counted in the drops and reported once;
    once the broker is back every update accepted before is delivered, in order."""
    with Broker(tmp_path) as broker, drives() as (bus, _sims):
        gate = Gate(broker)  # closed: the bridge cannot reach the broker
        extra = 'max_age = 0.001\noutbox_max_bytes = 65536\noutbox_policy = "refuse"'
        cfg = parse_bridge_config(toml(gate.url, bus.paths[0], tmp_path / "ob", extra), "b.toml")
        sub = Client(broker, ["pyrtu/e1/line/#"])
        events: list[BridgeEvent] = []

        async def main() -> tuple[int, int]:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            async with bridge:
                await until(lambda: bridge.refused > 20, "the outbox full")
                accepted = bridge.appended
                gate.open()
                await until(
                    lambda: bridge.stats()["outbox_depth"] == 0 and bridge.appended > accepted + 50,
                    "drained and accepting again",
                )
                return accepted, bridge.stats()["drops"]

        try:
            accepted, drops = aio_run(main())
        finally:
            gate.close()
        assert drops > 20
        errors = [e for e in events if e.kind == "outbox_error"]
        assert len(errors) == 1 and "full" in errors[0].detail["message"]
        sub.wait(lambda: len(seqs(sub)) >= accepted, "every accepted update")
        got = sorted(set(seqs(sub)))
        assert got[:accepted] == list(range(1, accepted + 1))
        sub.close()
