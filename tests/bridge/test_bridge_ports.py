"""The bridge and a bus's port that fails: the poller's own drop of the virtual bus
unplugged under a running bridge, through a real broker (mosquitto).  Every point
of the bus goes ``stale``, the slaves ``offline`` and the bus's status ``down``
with the error; back, the bus says ``up`` and values and slaves resume."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

from mqtt_broker import Broker, Client
from test_bridge_broker import POINTS, drives, last, toml, topic, until

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge, BridgeEvent
from pyrtu.drivers.aio import run as aio_run
from pyrtu.poller import PortState, Update

BUS = "pyrtu/e1/line/status"
SLAVES = ("pyrtu/e1/line/1/status", "pyrtu/e1/line/5/status")


def quality(sub: Client, name: str) -> str | None:
    doc = last(sub, topic(name))
    return None if doc is None else str(doc["quality"])


def bus_state(sub: Client) -> dict[str, Any] | None:
    got = sub.on(BUS)
    return json.loads(got[-1]) if got else None


def test_a_port_unplugged_makes_its_points_stale_and_they_resume(tmp_path: Path) -> None:
    with Broker(tmp_path) as broker, drives() as (bus, _sims):
        port = bus.paths[0]
        cfg = parse_bridge_config(toml(broker.url, port, tmp_path / "ob"), "b.toml")
        sub = Client(broker, ["pyrtu/#"])
        events: list[BridgeEvent] = []
        # the poller's own account, independent of the bridge's reporter: when each
        # point was last read before the port went down
        last_read: dict[str, float] = {}
        down_seen = False

        def reads(ev: object) -> None:
            nonlocal down_seen
            if isinstance(ev, PortState) and not ev.up:
                down_seen = True
            elif isinstance(ev, Update) and not down_seen:
                last_read[ev.point.name] = ev.time

        async def main() -> None:
            bridge = Bridge(cfg)
            bridge.on_event(events.append)
            bridge.poller.on_event(reads)
            async with bridge:
                await until(lambda: all(quality(sub, n) == "good" for n in POINTS), "values")
                await until(lambda: all(sub.on(t)[-1:] == [b"online"] for t in SLAVES), "online")
                await until(lambda: (bus_state(sub) or {}).get("state") == "up", "bus up")
                bus.unplug(0)  # the bridge's own adapter pulled out
                await until(lambda: all(quality(sub, n) == "stale" for n in POINTS), "stale")
                await until(lambda: all(sub.on(t)[-1:] == [b"offline"] for t in SLAVES), "off")
                await until(lambda: (bus_state(sub) or {}).get("state") == "down", "bus down")
                await asyncio.sleep(0.5)  # several reopening attempts meanwhile
                bus.replug(0)
                await until(lambda: (bus_state(sub) or {}).get("state") == "up", "bus up again")
                await until(lambda: all(quality(sub, n) == "good" for n in POINTS), "good again")
                await until(lambda: all(sub.on(t)[-1:] == [b"online"] for t in SLAVES), "online")

        aio_run(main())
        sub.close()
        msgs = list(sub.messages)
        docs = [json.loads(p) for t, p, *_ in msgs if t == BUS]
        states = [d["state"] for d in docs]
        # up (first values), down once for the outage, up again
        assert states[:1] == ["up"] and states.count("down") == 1, states
        d = next(d for d in docs if d["state"] == "down")
        assert d["port"] == port and d["error"] and d["since"] <= d["time"]
        u = docs[-1]
        assert u["state"] == "up" and u["since"] == d["since"] and u["time"] > d["time"]
        # stale: the last value read and when it was read (the last read, not the last
        # publication: an unchanged value read again is not published but is known
        # to be that value at that time), never a good value while down
        for n in POINTS:
            mine = [json.loads(p) for t, p, *_ in msgs if t == topic(n)]
            first_stale = next(i for i, m in enumerate(mine) if m["quality"] == "stale")
            before = mine[first_stale - 1]
            assert before["quality"] == "good"
            assert mine[first_stale]["value"] == before["value"]
            assert mine[first_stale]["time"] == last_read[n] >= before["time"]
            # exactly one stale per point, then good values read after the replug
            after = mine[first_stale + 1 :]
            assert after and all(m["quality"] == "good" for m in after)
            assert all(m["time"] > d["time"] for m in after)  # read after the outage
        # the slaves' statuses: offline once for the outage, online once it is over
        for t in SLAVES:
            got = [p for tt, p, *_ in msgs if tt == t]
            assert got == [b"online", b"offline", b"online"], (t, got)
        kinds = [(e.kind, e.detail.get("up")) for e in events if e.kind == "port"]
        assert kinds == [("port", False), ("port", True)]
        # a newcomer sees the bus's retained status
        with Client(broker, [BUS]) as late:
            late.wait(lambda: bool(late.on(BUS)), "retained bus status")
            assert json.loads(late.on(BUS)[-1])["state"] == "up"
