"""The bridge's benchmark (issue 19): throughput into mosquitto against a bare
paho-mqtt loop, latency from the wire to a subscriber with 8 buses polled flat
out, the wire kept as busy as the poller alone keeps it, a broker killed for
seconds, three edges into one shared subscription, one slave of eight unplugged,
a write from an MQTT client to the wire.

    python bench/bench_bridge.py [--seconds 5] [--outage 30] [--only throughput,...]

Every part starts its own mosquitto (tests/mqtt_broker.py: a generated config on a
free loopback port, stopped by pid); the buses are ``pyrtu vbus`` processes with
simulated CV100 drives (one ``pyrtu simulate`` process serving every bus), as in
bench/bench_client.py.  Writes the section "## Bridge (issue 19)" at the end of
bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path[:0] = [str(ROOT / "tests"), str(BENCH)]

import paho.mqtt.client as paho  # noqa: E402
from paho.mqtt.enums import CallbackAPIVersion  # noqa: E402

from mqtt_broker import Broker  # noqa: E402
from pyrtu.aio import run as aio_run  # noqa: E402
from pyrtu.bridge import parse_bridge_config  # noqa: E402
from pyrtu.bridge.bridge import Bridge  # noqa: E402
from pyrtu.bridge.topics import payload, record, split_record  # noqa: E402
from pyrtu.poller import Point, Poller, Update  # noqa: E402

RESULTS = BENCH / "RESULTS.md"
HEADING = "## Bridge (issue 19)"
BAUD = 115200
#: the CV100's status words and monitored values (U0): FC 03 0x3300 + 7 registers
CV_START, CV_COUNT = 0x3300, 7


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, max(0, int(round(q / 100 * len(s) + 0.5)) - 1))] if s else float("nan")


# ---------------------------------------------------------------------- throughput


def _points(n: int) -> list[Point]:
    return [Point(f"p{i:03d}", "bus", 1 + i // 50, "holding", i % 50) for i in range(n)]


def _config(url: str, outbox: Path, qos: int, port: str = "/dev/null", extra: str = "") -> str:
    return f"""
[mqtt]
url = "{url}"
edge = "bench"
outbox = "{outbox}"
qos = {qos}
stats_interval = 3600
{extra}
[[bus]]
name = "bus"
port = "{port}"
baudrate = {BAUD}
parity = "N"
timeout = 0.1
""" + "".join(
        f'[[point]]\nname = "{p.name}"\nbus = "bus"\nslave = {p.slave}\ntable = "holding"\n'
        f"address = {p.address}\n"
        for p in _points(200)
    )


def bridge_rate(url: str, tmp: Path, qos: int, n: int) -> dict[str, float]:
    """``n`` updates of 200 points fed to a bridge (reporter, outbox, publish) as
    fast as it acknowledges them; updates per second acknowledged."""
    cfg = parse_bridge_config(_config(url, tmp / f"ob-{qos}-{time.time_ns()}", qos), "bench")
    pts = _points(200)

    async def main() -> dict[str, float]:
        bridge = Bridge(cfg)
        await bridge.start(poll=False)
        while not bridge.stats()["connected"]:
            await asyncio.sleep(0.01)
        win = bridge._window
        ob = bridge._outbox
        assert ob is not None
        t0, c0 = time.perf_counter(), time.process_time()
        i = 0
        while i < n:
            if ob.depth > 4 * win.window:
                await asyncio.sleep(0)
                continue
            for _ in range(100):
                bridge.feed(Update(pts[i % 200], i, time.time()))
                i += 1
            await asyncio.sleep(0)
        while win.acknowledged < n:
            await asyncio.sleep(0.001)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        await bridge.stop()
        return {"per_s": n / wall, "cpu_us": 1e6 * cpu / n}

    return dict(aio_run(main()))


def bare_rate(port: int, qos: int, n: int) -> dict[str, float]:
    """The same topics and payloads published by paho-mqtt's own loop (loop_start),
    waiting for every acknowledgement (QoS 1) or every write (QoS 0)."""
    pts = _points(200)
    topics = [f"pyrtu/bench/bus/{p.slave}/{p.name}" for p in pts]
    bodies = [split_record(record(topics[i % 200], pts[i % 200], i, time.time(), "good"))[1]
              for i in range(200)]  # fmt: skip
    c = paho.Client(CallbackAPIVersion.VERSION2, client_id="bare", protocol=paho.MQTTv5)
    c.max_inflight_messages_set(1000)
    c.max_queued_messages_set(0)
    done = threading.Semaphore(0)
    acked = [0]

    def on_publish(*_: Any) -> None:
        acked[0] += 1
        if acked[0] == n:
            done.release()

    c.on_publish = on_publish
    c.connect("127.0.0.1", port, 30)
    c.loop_start()
    time.sleep(0.3)
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(n):
        c.publish(topics[i % 200], payload(bodies[i % 200], i, False), qos, True)
    done.acquire(timeout=120)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    c.disconnect()
    c.loop_stop()
    return {"per_s": n / wall, "cpu_us": 1e6 * cpu / n}


def throughput(tmp: Path, n: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    with Broker(tmp) as broker:
        for qos in (0, 1):
            bare = [bare_rate(broker.port, qos, n) for _ in range(2)]
            ours = [bridge_rate(broker.url, tmp, qos, n) for _ in range(2)]
            b = max(bare, key=lambda r: r["per_s"])
            o = max(ours, key=lambda r: r["per_s"])
            out[f"qos{qos}"] = {"bridge": o, "bare": b, "ratio": o["per_s"] / b["per_s"]}
    return out


# ---------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--updates", type=int, default=100_000)
    ap.add_argument("--only", default="throughput")
    ns = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        res: dict[str, Any] = {}
        if "throughput" in ns.only:
            res["throughput"] = throughput(tmp, ns.updates)
        print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
