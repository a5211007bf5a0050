"""The live path: a value the poller hands over reaches the broker's socket from
within that call (no timer, no fsync, no wait for the loop's next turn), against
a real broker (mosquitto)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from mqtt_broker import Broker, Client
from test_bridge_broker import until

from pyrtu.bridge import mqtt as bridge_mqtt
from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge
from pyrtu.drivers.aio import run as aio_run
from pyrtu.poller import Point, Update


def config(url: str, outbox: Path, qos: int) -> str:
    points = "".join(
        f'[[point]]\nname = "p{i}"\nbus = "bus"\nslave = 1\ntable = "holding"\naddress = {i}\n'
        for i in range(20)
    )
    return (
        f'[mqtt]\nurl = "{url}"\nedge = "e1"\noutbox = "{outbox}"\nqos = {qos}\n'
        "stats_interval = 3600\nfsync_interval = 3600\n"
        '[[bus]]\nname = "bus"\nport = "/dev/null"\nbaudrate = 19200\n' + points
    )


def test_a_live_value_is_written_to_the_socket_at_once(tmp_path: Path) -> None:
    """After `feed` returns, before the loop runs anything else, the value's
    PUBLISH has left the process (nothing queued in paho or in the link's buffer,
    the QoS 0 publication already counted as written); the outbox's fsync batch
    (an hour away here) is not waited for.  A burst beyond `IMMEDIATE` in one turn
    waits for the turn's end, then goes out too."""
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(config(broker.url, tmp_path / "ob", 0), "live.toml")
        points = [Point(f"p{i}", "bus", 1, "holding", i) for i in range(20)]
        sub = Client(broker, ["pyrtu/e1/bus/1/+"])

        async def main() -> tuple[list[int], int, int]:
            bridge = Bridge(cfg)
            await bridge.start(poll=False)
            try:
                await until(lambda: bridge.stats()["connected"], "connected")
                await asyncio.sleep(0.05)  # the connection's own packets out
                link = bridge._link
                assert link is not None
                pending = []
                for i in range(3):
                    bridge.feed(Update(points[i], i, 1.0))
                    pending.append(link.pending_writes)
                written = bridge._window.published
                acked = bridge._window.acknowledged
                await asyncio.sleep(0)
                # a burst: the first IMMEDIATE calls of a turn are written at once
                for i in range(3, 20):
                    bridge.feed(Update(points[i], i, 1.0))
                burst = link.pending_writes
                await until(lambda: bridge._window.acknowledged == 20, "the burst written")
                return [*pending, written, acked], burst, link.pending_writes
            finally:
                await bridge.stop()

        figures, burst, after = aio_run(main())
        *pending, written, acked = figures
        assert pending == [0, 0, 0]  # written from within feed, each
        assert (written, acked) == (3, 3)  # QoS 0: counted as written already
        assert 20 - 3 > bridge_mqtt.IMMEDIATE and burst > 0  # the rest at the turn's end
        assert after == 0
        sub.wait(lambda: all(sub.on(f"pyrtu/e1/bus/1/p{i}") for i in range(20)), "all 20")
        sub.close()
        got = [json.loads(sub.on(f"pyrtu/e1/bus/1/p{i}")[-1])["value"] for i in range(20)]
        assert got == list(range(20))
