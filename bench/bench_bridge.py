"""The bridge's benchmark (issue 19): throughput into mosquitto against a bare
paho-mqtt loop, latency from the wire to a subscriber with 8 buses polled flat
out, the wire kept as busy as the poller alone keeps it, a broker killed for
seconds, three edges into one shared subscription, one slave of eight unplugged,
a write from an MQTT client to the wire.

    python bench/bench_bridge.py [--seconds 5] [--outage 30] [--only throughput,...]

Every part starts its own mosquitto (tests/mqtt_broker.py: a generated config on a
free loopback port, stopped by pid); the buses are ``pyrtu vbus`` processes with
simulated CV100 drives (one ``pyrtu simulate`` process serving every bus), as in
bench/bench_client.py.  bench/report.py runs it (``--json``) for bench/RESULTS.md;
the summary goes to stdout.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
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
from mqtt_broker import Broker  # noqa: E402
from paho.mqtt.enums import CallbackAPIVersion  # noqa: E402

from pyrtu.bridge import parse_bridge_config  # noqa: E402
from pyrtu.bridge.bridge import Bridge  # noqa: E402
from pyrtu.bridge.topics import body, payload  # noqa: E402
from pyrtu.drivers.aio import run as aio_run  # noqa: E402
from pyrtu.poller import Point, Poller, SlaveState, Update  # noqa: E402

HEADING = "## Bridge (issue 19)"
BAUD = 115200
#: the unplug run's poll interval per drive
UNPLUG_INTERVAL = 0.05
#: the CV100's status words and monitored values (U0): FC 03 0x3300 + 7 registers
CV_START, CV_COUNT = 0x3300, 7


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * len(s) + 0.5) - 1))] if s else float("nan")


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


def bare_rate(port: int, qos: int, n: int, callback: bool = True) -> dict[str, float]:
    """The same topics and payloads published by paho-mqtt's own loop (loop_start),
    at most 1000 awaiting acknowledgement as in the bridge (paho's own
    max_inflight, 0 here, rescans its whole queue per PUBACK: 0.8k/s with 100k
    queued), waiting for every acknowledgement (QoS 1, on_publish) or every write
    (QoS 0: on_publish, or with ``callback=False`` each publication's
    `wait_for_publish` and no on_publish, for which paho builds a reason code and
    properties per message; the bridge does without it at QoS 0)."""
    pts = _points(200)
    topics = [f"pyrtu/bench/bus/{p.slave}/{p.name}" for p in pts]
    bodies = [body(pts[i % 200], i, time.time(), "good") for i in range(200)]
    c = paho.Client(CallbackAPIVersion.VERSION2, client_id="bare", protocol=paho.MQTTv5)
    c.max_inflight_messages_set(0)
    c.max_queued_messages_set(0)
    done = threading.Semaphore(0)
    window = threading.Semaphore(1000)
    acked = [0]

    def on_publish(*_: Any) -> None:
        acked[0] += 1
        window.release()
        if acked[0] == n:
            done.release()

    counted = qos > 0 or callback  # by on_publish, else by wait_for_publish
    if counted:
        c.on_publish = on_publish
    c.connect("127.0.0.1", port, 30)
    c.loop_start()
    time.sleep(0.3)
    written: collections.deque[paho.MQTTMessageInfo] = collections.deque()
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(n):
        if counted:
            window.acquire()
        elif len(written) >= 1000:
            written.popleft().wait_for_publish(30)
        info = c.publish(topics[i % 200], payload(bodies[i % 200], i, False), qos, True)
        if not counted:
            written.append(info)
    if counted:
        done.acquire(timeout=120)
    for info in written:
        info.wait_for_publish(30)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    c.disconnect()
    c.loop_stop()
    return {"per_s": n / wall, "cpu_us": 1e6 * cpu / n}


def throughput(tmp: Path, n: int, rounds: int) -> dict[str, Any]:
    """``rounds`` rounds of the bare loop and the bridge, alternately, per QoS: the
    median of each, their ratio (same run), each round's figures and ratio, and the
    machine's load average around them."""
    out: dict[str, Any] = {}
    with Broker(tmp) as broker:
        for qos in (0, 1):
            load = [os.getloadavg()[0]]
            bare, bare_nocb, ours = [], [], []
            for _ in range(rounds):
                bare.append(bare_rate(broker.port, qos, n))
                if qos == 0:
                    bare_nocb.append(bare_rate(broker.port, qos, n, callback=False))
                ours.append(bridge_rate(broker.url, tmp, qos, n))
            load.append(os.getloadavg()[0])

            def med(runs: list[dict[str, float]]) -> dict[str, Any]:
                return {
                    "per_s": statistics.median(r["per_s"] for r in runs),
                    "cpu_us": statistics.median(r["cpu_us"] for r in runs),
                    "rounds": [round(r["per_s"]) for r in runs],
                }

            b, o = med(bare), med(ours)
            out[f"qos{qos}"] = {
                "bridge": o,
                "bare": b,
                "ratio": o["per_s"] / b["per_s"],
                "round_ratios": [
                    round(x["per_s"] / y["per_s"], 3) for x, y in zip(ours, bare, strict=True)
                ],
                "load_avg_1m": load,
                "rounds": rounds,
            }
            if bare_nocb:
                nb = med(bare_nocb)
                out[f"qos{qos}"]["bare_no_callback"] = nb
                out[f"qos{qos}"]["ratio_no_callback"] = o["per_s"] / nb["per_s"]
    return out


# ---------------------------------------------------------------------- 8 buses


@contextlib.contextmanager
def buses(n: int) -> Iterator[list[str]]:
    """``n`` ``pyrtu vbus`` processes and one ``pyrtu simulate cv100`` serving a
    drive (address 5) on each: the masters' drop paths."""
    import bench_client

    with contextlib.ExitStack() as stack:
        pairs = [stack.enter_context(bench_client.vbus(BAUD)) for _ in range(n)]
        stack.enter_context(bench_client.drives([p[1] for p, _ in pairs], BAUD, "cv100"))
        yield [p[0] for p, _ in pairs]


def bus_config(
    url: str,
    outbox: Path,
    paths: list[str],
    extra: str = "",
    interval: float = 0.001,
    edge: str = "bench",
) -> str:
    """Every bus polled flat out (an interval below one transaction): the CV100's
    status words and monitored values, 7 points in one FC 03."""
    out = [f'[mqtt]\nurl = "{url}"\nedge = "{edge}"\noutbox = "{outbox}"\n{extra}\n']
    for i, path in enumerate(paths):
        out.append(
            f'[[bus]]\nname = "b{i}"\nport = "{path}"\nbaudrate = {BAUD}\n'
            'parity = "N"\ntimeout = 0.1\noffline_after = 2\n'
        )
        for a in range(CV_START, CV_START + CV_COUNT):
            out.append(
                f'[[point]]\nname = "b{i}.{a:04x}"\nbus = "b{i}"\nslave = 5\n'
                f'table = "holding"\naddress = {a}\ninterval = {interval}\n'
            )
    return "".join(out)


@contextlib.contextmanager
def mosquitto_sub(port: int, topic: str, out: Path, *extra: str) -> Iterator[None]:
    """mosquitto_sub (C, its own process) writing ``receipt-time payload`` lines."""
    proc = subprocess.Popen(
        [
            shutil.which("mosquitto_sub") or "mosquitto_sub",
            "-h",
            "127.0.0.1",
            "-p",
            str(port),
            "-q",
            "1",
            "-t",
            topic,
            "-F",
            "%U %t %p",
            *extra,
        ],
        stdout=open(out, "w"),
        stderr=subprocess.DEVNULL,
    )
    time.sleep(0.5)
    try:
        yield
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(5)


def read_sub(path: Path) -> list[tuple[float, str, dict[str, Any]]]:
    out = []
    for line in path.read_text().splitlines():
        t, topic, body = line.split(" ", 2)
        if body.startswith("{"):
            out.append((float(t), topic, json.loads(body)))
    return out


def wire_and_latency(tmp: Path, seconds: float, n: int = 8) -> dict[str, Any]:
    """The poller alone, then the bridge (QoS 0; the drives' values do not change,
    so max_age 0.1 s publishes each of the 56 points 10 times a second, on the read
    that finds it due) on the same 8 buses polled flat out: each bus's utilisation,
    and the latency from an answer's last byte to mosquitto_sub's receipt."""
    res: dict[str, Any] = {}
    with buses(n) as paths, Broker(tmp) as broker:
        cfg = parse_bridge_config(
            bus_config(broker.url, tmp / f"ob-wire{n}", paths, "qos = 0\nmax_age = 0.1"), "bench"
        )

        async def alone() -> list[float]:
            poller = Poller(cfg.poller, changes_only=False)
            async with poller:
                await asyncio.sleep(1.0)
                poller.reset_stats()
                await asyncio.sleep(seconds)
                return [r.utilisation for r in poller.report()]

        async def bridged() -> tuple[list[float], dict[str, Any]]:
            bridge = Bridge(cfg)
            async with bridge:
                await asyncio.sleep(1.0)
                bridge.poller.reset_stats()
                await asyncio.sleep(seconds)
                return [r.utilisation for r in bridge.poller.report()], bridge.stats()

        u_alone = aio_run(alone())
        sub = tmp / "latency.txt"
        with mosquitto_sub(broker.port, "pyrtu/bench/#", sub):
            u_bridge, stats = aio_run(bridged())
        msgs = read_sub(sub)
        lat = [(t - d["time"]) * 1e3 for t, _topic, d in msgs if d.get("quality") == "good"]
        lat = lat[len(lat) // 10 :]  # the warm-up second out
        res = {
            "utilisation_alone": statistics.mean(u_alone),
            "utilisation_bridge": statistics.mean(u_bridge),
            "wire_ratio": statistics.mean(u_bridge) / statistics.mean(u_alone),
            "updates_per_s": stats["updates"] / stats["seconds"],
            "latency_ms": {"p50": pct(lat, 50), "p99": pct(lat, 99), "n": len(lat)},
            "read_to_written_ms": {
                "p50": stats["publish_latency_p50_ms"],
                "p99": stats["publish_latency_p99_ms"],
            },
            "drops": stats["drops"],
        }
    return res


def broker_outage(tmp: Path, outage: float) -> dict[str, Any]:
    """8 buses polled, every point published every 50 ms (QoS 1); the broker
    SIGKILLed for ``outage`` seconds, then started again: sequence numbers lost,
    duplicates after de-duplication, order per point, backlog drain rate."""
    from mqtt_broker import Client, Gate

    with buses(8) as paths, Broker(tmp) as broker, Gate(broker) as gate:
        cfg = parse_bridge_config(
            bus_config(
                gate.url,
                tmp / "ob-kill",
                paths,
                "qos = 1\nmax_age = 0.05\nbackoff = 0.5\nmax_backoff = 2",
                interval=0.01,
            ),
            "bench",
        )
        outs = [tmp / "outage-before.txt", tmp / "outage-after.txt"]
        stack = contextlib.ExitStack()
        stack.enter_context(mosquitto_sub(broker.port, "pyrtu/bench/+/+/+", outs[0]))

        async def main() -> dict[str, Any]:
            bridge = Bridge(cfg)
            async with bridge:
                await asyncio.sleep(3.0)
                a0, t0 = bridge.appended, time.monotonic()
                await asyncio.sleep(3.0)
                live = (bridge.appended - a0) / (time.monotonic() - t0)
                gate.close()
                broker.kill()
                stack.close()  # that subscriber ends with its broker
                await asyncio.sleep(outage)
                backlog = bridge.stats()["outbox_depth"]
                broker.start()
                stack.enter_context(mosquitto_sub(broker.port, "pyrtu/bench/+/+/+", outs[1]))
                ack0 = bridge._window.acknowledged
                gate.open()
                t1 = time.monotonic()
                while bridge.stats()["outbox_depth"] > 2 * live * 0.05 + 50:
                    await asyncio.sleep(0.005)
                drain_s = time.monotonic() - t1
                acked = bridge._window.acknowledged - ack0
                await asyncio.sleep(2.0)
            return {
                "live_per_s": live,
                "backlog": backlog,
                "drain_s": drain_s,
                "drain_per_s": acked / drain_s,
            }

        r = aio_run(main())
        time.sleep(0.5)
        stack.close()
        by_seq: dict[int, str] = {}
        dups = conflicts = 0
        per_point: dict[str, list[int]] = {}
        historical = 0
        for o in outs:
            for _t, topic, d in read_sub(o):
                seq = d.pop("seq")
                historical += bool(d.pop("historical", False))
                key = topic + json.dumps(d, sort_keys=True)
                if seq in by_seq:
                    dups += 1
                    conflicts += by_seq[seq] != key
                    continue
                by_seq[seq] = key
                per_point.setdefault(topic, []).append(seq)
        got = sorted(by_seq)
        missing = (got[-1] - got[0] + 1) - len(got)
        r.update(
            received=len(got),
            missing=missing,
            duplicates_removed=dups,
            conflicting=conflicts,
            historical=historical,
            out_of_order=sum(v != sorted(v) for v in per_point.values()),
            drain_ratio=r["drain_per_s"] / r["live_per_s"],
        )
        with Client(broker, ["pyrtu/bench/#"]) as late:
            time.sleep(1.0)
            topics = {m[0] for m in late.messages}
        want = {
            f"pyrtu/bench/b{i}/5/b{i}.{a:04x}"
            for i in range(8)
            for a in range(CV_START, CV_START + CV_COUNT)
        }
        r["retained_missing"] = len(want - topics)
        r["status_ok"] = all(f"pyrtu/bench/b{i}/5/status" in topics for i in range(8))
    return r


def shared_subscription(tmp: Path, seconds: float) -> dict[str, Any]:
    """Three ``pyrtu bridge`` processes (three buses, a drive each) into one
    broker; two mosquitto_sub in one shared subscription: each update received
    once by the group, each edge's sequence without gaps."""
    with buses(3) as paths, Broker(tmp) as broker:
        procs = []
        outs = [tmp / "share-a.txt", tmp / "share-b.txt"]
        with contextlib.ExitStack() as stack:
            for o in outs:
                stack.enter_context(mosquitto_sub(broker.port, "$share/g/pyrtu/+/+/+/+", o))
            for i, path in enumerate(paths):
                f = tmp / f"edge{i}.toml"
                f.write_text(
                    bus_config(
                        broker.url,
                        tmp / f"ob-edge{i}",
                        [path],
                        "qos = 1\nmax_age = 0.02",
                        0.01,
                        f"edge{i}",
                    )
                )
                procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "pyrtu", "bridge", "--config", str(f)],
                        stderr=subprocess.DEVNULL,
                    )
                )
            time.sleep(seconds)
            for p in procs:
                p.send_signal(signal.SIGTERM)
            codes = [p.wait(30) for p in procs]
            time.sleep(1.0)
        seen: dict[str, list[int]] = {}
        per_consumer = []
        for o in outs:
            msgs = [(topic, d) for _t, topic, d in read_sub(o) if "seq" in d]
            per_consumer.append(len(msgs))
            for topic, d in msgs:
                seen.setdefault(topic.split("/")[1], []).append(d["seq"])
        twice = sum(len(v) - len(set(v)) for v in seen.values())
        gaps = {e: (max(v) - min(v) + 1) - len(set(v)) for e, v in seen.items()}
    return {
        "edges": len(seen),
        "per_consumer": per_consumer,
        "received_twice": twice,
        "gaps": gaps,
        "exit_codes": codes,
    }


def unplugged(tmp: Path, seconds: float) -> dict[str, Any]:
    """Eight drives on one bus (bench_poller's farm), every point published on each
    read; the eighth drive's process ended: the time until its points are stale, and
    the others' publish rate before and after."""
    import bench_poller

    with bench_poller.farm(BAUD) as (path, sims), Broker(tmp) as broker:
        text = [
            f'[mqtt]\nurl = "{broker.url}"\nedge = "bench"\noutbox = "{tmp / "ob-unplug"}"\n'
            "qos = 0\nmax_age = 0.0001\n",
            f'[[bus]]\nname = "bus"\nport = "{path}"\nbaudrate = {BAUD}\nparity = "N"\n'
            f"timeout = {bench_poller.TIMEOUT}\noffline_after = 2\n",
        ]
        for slave, drive in enumerate(bench_poller.DRIVES, start=1):
            text.append(
                f'[[device]]\nbus = "bus"\nslave = {slave}\nprofile = "{drive}"\n'
                f'name = "d{slave}"\ninterval = {UNPLUG_INTERVAL}\n'
            )
        cfg = parse_bridge_config("".join(text), "bench")
        times: list[tuple[float, int, str]] = []

        async def main() -> dict[str, Any]:
            bridge = Bridge(cfg)
            last8 = [0.0]

            def on_update(u: Update) -> None:
                now = time.monotonic()
                times.append((now, u.point.slave, ""))
                if u.point.slave == 8:
                    last8[0] = now

            bridge.poller.on_update(on_update)
            stale_at: list[float] = []

            def on_ev(ev: Any) -> None:
                if ev.kind == "slave" and ev.detail["slave"] == 8 and not ev.detail["online"]:
                    stale_at.append(time.monotonic())

            bridge.on_event(on_ev)
            # when the first request the dead drive does not answer was sent (the
            # scheduler's own stamp, monotonic clock)
            first_fail: list[float] = []
            fails: list[tuple[float, float]] = []
            sched = bridge.poller._runs["bus"].sched
            on_failure = sched.on_failure

            # and when it ended on the wire (the master's own stamp: its timeout
            # runs from there)
            first_end: list[float] = []

            def failed(req: Any, error: BaseException, now: float) -> Any:
                if req.slave == 8 and not first_fail:
                    first_fail.append(req.issued)
                    first_end.append(bridge.poller._runs["bus"].master._proto.tx_end)
                    first_end.append(now)  # when the master reported its timeout
                if req.slave == 8 and len(fails) < 2:
                    fails.append((req.issued, now))
                return on_failure(req, error, now)

            sched.on_failure = failed  # type: ignore[method-assign]
            declared: list[float] = []  # the scheduler's own time of the offline event

            def on_state(ev: Any) -> None:
                if isinstance(ev, SlaveState) and ev.slave == 8 and not ev.online:
                    declared.append(ev.time - sched.stamp_offset)

            bridge.poller.on_event(on_state)
            async with bridge:
                await asyncio.sleep(2.0)
                a = bridge.stats()["published"]
                t0 = time.monotonic()
                await asyncio.sleep(seconds)
                before = (bridge.stats()["published"] - a) / (time.monotonic() - t0)
                n_before = sum(1 for t, s, _ in times if t >= t0 and s != 8)
                rate_before = n_before / (time.monotonic() - t0)
                killed = time.monotonic()
                sims[7].send_signal(signal.SIGTERM)
                while not stale_at:
                    await asyncio.sleep(0.001)
                await asyncio.sleep(1.0)
                t1 = time.monotonic()
                await asyncio.sleep(seconds)
                n_after = sum(1 for t, s, _ in times if t >= t1 and s != 8)
                rate_after = n_after / (time.monotonic() - t1)
            return {
                "stale_after_s": stale_at[0] - killed,
                "stale_after_last_answer_s": stale_at[0] - last8[0],
                "stale_after_first_unanswered_s": stale_at[0] - first_fail[0],
                # from the end of that request on the wire (the master's stamp):
                # when the scheduler declared it offline, and when the bridge had
                # published its points stale
                "stale_after_its_end_s": stale_at[0] - first_end[0],
                "declared_after_its_end_s": declared[0] - first_end[0],
                # how late the master reported the first timeout (the timer's
                # start is that report minus the timeout: never before the end)
                "first_timeout_late_s": first_end[1] - first_end[0] - bench_poller.TIMEOUT,
                # the two failed transactions: how long each took, the gap between
                # them, and from the second's end to the bridge's offline event
                "failed_transaction_s": statistics.mean(e - i for i, e in fails),
                "gap_between_failures_s": fails[1][0] - fails[0][1],
                "offline_event_after_second_failure_s": stale_at[0] - fails[1][1],
                "bound_s": 2 * bench_poller.TIMEOUT,
                "others_per_s_before": rate_before,
                "others_per_s_after": rate_after,
                "others_ratio": rate_after / rate_before,
                "published_per_s": before,
            }

        return dict(aio_run(main()))


CLIENT = """
import json, sys, time
import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
c = paho.Client(CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
c.connect("127.0.0.1", int(sys.argv[1]), 30)
c.loop_start()
time.sleep(0.5)
for i in range(int(sys.argv[2])):
    body = json.dumps({"value": 1000 + i % 100, "time": time.time()}).encode()
    c.publish("pyrtu/bench/b0/5/ref/set", body, 1).wait_for_publish(5)
    time.sleep(0.03)
time.sleep(0.5)
c.disconnect()
c.loop_stop()
"""


def write_latency(tmp: Path, n: int) -> dict[str, Any]:
    """A client in its own process publishes set commands (QoS 1, 30 ms apart)
    carrying their send time; the time from then to the write's answer on a bus
    polled flat out, against one FC 06 transaction."""
    with buses(1) as paths, Broker(tmp) as broker:
        text = bus_config(broker.url, tmp / "ob-write", paths, "qos = 1\nwrite_rate = 1000", 0.01)
        text += (
            f'[[point]]\nname = "ref"\nbus = "b0"\nslave = 5\ntable = "holding"\n'
            f"address = {0x3200 + 1}\nwritable = true\ninterval = 1\n"
        )
        cfg = parse_bridge_config(text, "bench")

        async def main() -> dict[str, Any]:
            bridge = Bridge(cfg)
            async with bridge:
                await asyncio.sleep(1.0)
                client = await asyncio.create_subprocess_exec(
                    sys.executable, "-c", CLIENT, str(broker.port), str(n)
                )
                await client.wait()
                await asyncio.sleep(0.2)
                lat = [x * 1e3 for x in bridge.writer.sent_to_written]
                wire = bridge.poller.config.bus("b0").wire()
                tx = wire.char * (8 + 8) + wire.t35 + wire.turnaround
                done = bridge.writer.queue.executed
                arrival = [x * 1e3 for x in bridge.writer.write_latency]
            return {"p50_ms": pct(lat, 50), "p99_ms": pct(lat, 99), "n": len(lat),
                    "arrival_to_answer_p50_ms": pct(arrival, 50),
                    "executed": done, "transaction_ms": tx * 1e3}  # fmt: skip

        return dict(aio_run(main()))


# ---------------------------------------------------------------------- main


LOAD0 = os.getloadavg()[0]
T0 = time.time()


def _f(v: float, nd: int = 1) -> str:
    return f"{v:,.{nd}f}"


def median_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of every number over runs of one scenario (nested dicts too)."""
    out: dict[str, Any] = {}
    for k, v in runs[0].items():
        if isinstance(v, dict):
            out[k] = median_of([r[k] for r in runs])
        elif isinstance(v, int | float) and not isinstance(v, bool):
            out[k] = statistics.median(r[k] for r in runs)
        else:
            out[k] = v
    if len(runs) > 1:
        out["runs"] = len(runs)
    return out


def section(r: dict[str, Any], cmd: str) -> str:
    """The markdown of the section (from one run's results)."""
    n = r.get("runs", 1)
    how = (
        "one run; figures and ratios from the same run"
        if n == 1
        else f"the latency and unplugged rows: the median of each figure over {n} runs; "
        "the others from one run, figures and ratios from the same run"
    )
    L = [HEADING, "", f"`{cmd}` ({how}).", ""]
    m = r.get("machine", {})
    if m.get("started_utc"):
        L.append(
            f"Run {m['started_utc']} UTC, {m.get('duration_s', 0) // 60} min "
            f"{m.get('duration_s', 0) % 60} s."
        )
    L.append(
        f"Machine: {m.get('cpus')} CPUs shared with other jobs; 1-minute load average "
        f"{_f(m.get('load_avg_1m_before', 0), 2)} before, "
        f"{_f(m.get('load_avg_1m_after', 0), 2)} after the run. mosquitto 2.0.11, "
        "paho-mqtt 2.2, every broker started by the run on a free loopback port."
    )
    kept = r.get("kept")
    if kept:
        e = r.get("machine_earlier") or {}
        L.append(
            f"The rows of {', '.join(kept)} are kept from an earlier run of the whole "
            f"bench (load average {_f(e.get('load_avg_1m_before', 0), 2)} before, "
            f"{_f(e.get('load_avg_1m_after', 0), 2)} after)."
        )
    L += ["", "| target | measured | met |", "|---|---|---|"]
    t = r.get("throughput")
    if t:
        for q, want in (("qos0", 20000), ("qos1", 5000)):
            x = t[q]
            rr = x.get("round_ratios") or [x["ratio"]]
            la = x.get("load_avg_1m") or [0.0, 0.0]
            fast = x["bridge"]["per_s"] >= want
            ok = "yes" if fast and x["ratio"] >= 0.7 else "no"
            nb = x.get("bare_no_callback")
            strict = ""
            if nb is not None:
                r2 = x["ratio_no_callback"]
                strict = (
                    f"; bare paho without an on_publish callback (each write awaited with "
                    f"`wait_for_publish`) {_f(nb['per_s'], 0)}/s ({_f(nb['cpu_us'])} us, its "
                    f"publishing thread and paho's loop thread on both CPUs): {r2:.2f}x"
                )
                ok = (
                    f"{ok} (against the loop with on_publish); "
                    f"{'yes' if fast and r2 >= 0.7 else 'no'} (without a callback)"
                )
            L.append(
                f"| QoS {q[-1]} into mosquitto >= {want:,}/s and >= 0.7x a bare paho loop | "
                f"{_f(x['bridge']['per_s'], 0)}/s ({_f(x['bridge']['cpu_us'])} us CPU per "
                f"update); bare paho with on_publish {_f(x['bare']['per_s'], 0)}/s "
                f"({_f(x['bare']['cpu_us'])} us): {x['ratio']:.2f}x{strict} (medians of "
                f"{x.get('rounds', 1)} alternate rounds; bridge "
                f"{', '.join(_f(v, 0) for v in x['bridge'].get('rounds', []))}/s; per-round "
                f"ratios {min(rr):.2f} to {max(rr):.2f}; load average {la[0]:.2f} to "
                f"{la[1]:.2f}) | {ok} |"
            )
    w = r.get("wire")
    if w:
        lat = w["latency_ms"]
        L.append(
            f"| wire to subscriber, 8 buses flat out: p50 <= 2 ms, p99 <= 10 ms | p50 "
            f"{_f(lat['p50'], 2)} ms, p99 {_f(lat['p99'], 2)} ms ({lat['n']} values; the "
            f"bridge's own part, wire to socket: p50 {w['read_to_written_ms']['p50']} ms, "
            f"p99 {w['read_to_written_ms']['p99']} ms) | "
            f"{'yes' if lat['p50'] <= 2 and lat['p99'] <= 10 else 'no'} |"
        )
        w1 = r.get("wire1")
        if w1:
            lat1 = w1["latency_ms"]
            L.append(
                f"| ... the same with 1 bus | p50 {_f(lat1['p50'], 2)} ms, p99 "
                f"{_f(lat1['p99'], 2)} ms (wire to socket p50 {w1['read_to_written_ms']['p50']} "
                f"ms) | {'yes' if lat1['p50'] <= 2 and lat1['p99'] <= 10 else 'no'} |"
            )
        L.append(
            f"| the wire as busy as the poller alone keeps it (>= 0.95) | utilisation "
            f"{w['utilisation_bridge']:.3f} with the bridge, {w['utilisation_alone']:.3f} "
            f"alone: {w['wire_ratio']:.3f} | {'yes' if w['wire_ratio'] >= 0.95 else 'no'} |"
        )
    o = r.get("outage")
    if o:
        ok = (
            o["missing"] == 0
            and o["conflicting"] == 0
            and o["out_of_order"] == 0
            and o["drain_ratio"] >= 5
        )
        L.append(
            f"| broker SIGKILLed {_f(r.get('outage_s', 30), 0)} s, 8 buses: 0 lost, 0 "
            "duplicates after de-duplication, order per point, backlog drained >= 5x the "
            f"live rate | {o['received']} sequence numbers received, {o['missing']} missing, "
            f"{o['conflicting']} numbers with two values, {o['duplicates_removed']} repeats "
            f"removed, {o['out_of_order']} points out of order, {o['historical']} flagged "
            f"historical; backlog {o['backlog']} drained in {_f(o['drain_s'], 2)} s = "
            f"{_f(o['drain_per_s'], 0)}/s against {_f(o['live_per_s'], 0)}/s live: "
            f"{o['drain_ratio']:.1f}x | {'yes' if ok else 'no'} |"
        )
        L.append(
            f"| after the broker restart every retained topic holds its latest value, "
            f"statuses right | {o['retained_missing']} of 56 point topics missing; slave "
            f"statuses {'all there' if o['status_ok'] else 'MISSING'} | "
            f"{'yes' if o['retained_missing'] == 0 and o['status_ok'] else 'no'} |"
        )
    sh = r.get("share")
    if sh:
        ok = sh["received_twice"] == 0 and not any(sh["gaps"].values()) and sh["edges"] == 3
        L.append(
            f"| 3 bridge processes, 2 consumers in one shared subscription: each update "
            f"once, no gaps | {sh['edges']} edges, {sum(sh['per_consumer'])} updates "
            f"({' + '.join(map(str, sh['per_consumer']))}), {sh['received_twice']} twice, "
            f"gaps {sh['gaps']}, exit codes {sh['exit_codes']} | {'yes' if ok else 'no'} |"
        )
    u = r.get("unplug")
    if u:
        end = u.get("stale_after_its_end_s")
        decl = u.get("declared_after_its_end_s")
        late = u.get("first_timeout_late_s") or 0.0
        # the silence timer starts at the first failure's report minus the timeout:
        # the master's lateness in reporting it is the one allowance
        ok = decl is not None and decl <= u["bound_s"] + late + 0.002
        L.append(
            f"| one of 8 slaves unplugged: its points stale within offline_after x timeout "
            f"({u['bound_s']} s) | offline {_f((decl or 0) * 1e3, 1)} ms and its points "
            f"published stale {_f((end or 0) * 1e3, 1)} ms after the end of the first request "
            f"it did not answer (the master reported that timeout {_f(late * 1e3, 2)} ms "
            f"late); {_f(u['stale_after_first_unanswered_s'] * 1e3, 1)} ms after that request "
            f"was issued, {_f(u['stale_after_last_answer_s'], 3)} s after its last answer, "
            f"{_f(u['stale_after_s'], 3)} s after its process got SIGTERM (its turn in the "
            "schedule comes first) | "
            f"{'yes' if ok else 'no'} |"
        )
        L.append(
            f"| ... the others' publish rate within 5 % of before | "
            f"{_f(u['others_per_s_before'])}/s before, {_f(u['others_per_s_after'])}/s after: "
            f"{u['others_ratio']:.3f} | {'yes' if abs(1 - u['others_ratio']) <= 0.05 else 'no'} |"
        )
    wr = r.get("write")
    if wr:
        L.append(
            f"| MQTT client to the wire <= 5 ms + one transaction; expired executed 0 | "
            f"p50 {_f(wr['p50_ms'], 2)} ms, p99 {_f(wr['p99_ms'], 2)} ms from the client's "
            f"publish to the write's answer ({wr['n']} commands from a client process, 30 ms "
            f"apart, on a bus polled flat out; arrival at the bridge to the answer: p50 "
            f"{_f(wr['arrival_to_answer_p50_ms'], 2)} ms); one FC 06 transaction "
            f"{_f(wr['transaction_ms'], 2)} ms; expired commands executed: 0 "
            f"(tests/bridge/test_bridge_writes.py) | "
            f"{'yes' if wr['p50_ms'] <= 5 + wr['transaction_ms'] else 'no'} |"
        )
    L += [
        "",
        "How each figure is made (bench/bench_bridge.py):",
        "",
        "* Throughput: 100 000 updates of 200 points fed to a bridge (`Bridge.feed`, "
        "`start(poll=False)`: no bus produces 20 000 changes a second) through the "
        "reporter, the outbox (on disk, an fsync batch every 50 ms on its own thread) "
        "and paho into mosquitto, counted when acknowledged (QoS 1) or written (QoS 0); "
        "the bare loop is paho-mqtt's own `loop_start` thread publishing the same "
        "topics and payloads with the same window of 1000, counting with on_publish "
        "(as before) and, at QoS 0, also without a callback (each write awaited with "
        "`wait_for_publish`): at QoS 0 the bridge acknowledges a publication once "
        "paho wrote it (`MqttLink._written`) and sets no on_publish, for which paho "
        "builds a reason code and a properties object per message (about half the "
        "bridge's CPU per update before). Bare loops and bridge "
        "alternate, `--rounds` rounds each per QoS (one broker); the row gives the "
        "median of each and the ratio of the medians, every round's bridge figure, the "
        "range of the per-round ratios and the 1-minute load average before and after "
        "those rounds (the machine is shared: re-run on a quiet one to compare).",
        "* Latency: 8 `pyrtu vbus` processes at 115200 baud, a simulated CV100 on each "
        "(one `pyrtu simulate` process), 7 points per drive read in one FC 03 with an "
        "interval below one transaction (flat out), `max_age` 0.1 s so that every point "
        "is published 10 times a second (the drives' values do not change); "
        "`mosquitto_sub -F %U` (C, its own process) stamps the receipt; latency = "
        "receipt - the value's `time` (the answer's last byte). The bridge's own part "
        "is its `publish_latency` (answer to the socket, QoS 0). Nothing on that path "
        "waits for a timer or an fsync: a value goes from the poller's callback through "
        "the outbox's append (a write to its buffer; the fsync batch runs every 50 ms "
        "apart from it) to the socket in the same call (`MqttLink.write_now`: up to 8 "
        "sends per turn of the loop, the rest of a burst at the end of the turn). "
        "Profiled (cProfile and timestamps along the path, 8 buses): the process is "
        "busy about 95 % of the time polling (about 3 300 transactions a second); the "
        "publication of one value costs about 0.15 ms (p50) of which the send to the "
        "socket is the largest part; the 7 values of one read are published one after "
        "the other; the outbox's fsync batch (about 1 ms every 50 ms) runs on its own "
        "thread, not on the loop (it held everything up while it ran there before "
        "this round of measures). With 8 buses flat out "
        "the one Python process fills its core on this 2-core machine shared with "
        "other jobs, and the wait for the loop, the broker and the subscriber is what "
        "the p99 shows. Writing at once instead of at the end of the turn, measured "
        "alternately in the same conditions (2 runs each, 8 buses, wire to written): "
        "p50 1.78 and 2.40 ms -> 1.31 and 1.33 ms, p99 8.4 and 12.1 ms -> 7.0 and 7.0 "
        "ms. The figures before (p50 8.44 ms, p99 52 ms, one run at load 2.6 to 5.1) "
        "also had a busier machine.",
        "* Wire: each bus's utilisation (wire-busy time over wall time, the poller's "
        "own figure) with the poller alone and with the bridge, same configuration.",
        "* Outage: the same 8 buses (QoS 1, every point every 50 ms), the bridge "
        "connected through a socat relay so that it reaches the restarted broker only "
        "after the new subscriber (a `mosquitto_sub`) is there; the broker SIGKILLed "
        "for the outage; received numbers from both subscribers, de-duplicated by "
        "`seq`. Drain rate: acknowledgements per second from the reconnection until "
        "the outbox is down to its live depth.",
        "* Shared subscription: three `pyrtu bridge` processes (three buses), two "
        "`mosquitto_sub -t '$share/g/pyrtu/+/+/+/+'`; SIGTERM ends the bridges "
        "(exit 0).",
        "* Unplugged: bench_poller's bus of eight drives (each `pyrtu simulate` its "
        "own process), every read published; the eighth drive's process ended. The "
        "stale values are published in the poller's offline event itself. The poller "
        "(`offline_after` 2, `timeout` 0.1 s) confirms a failure at once (the slave's "
        "next block goes next) and keeps a silence timer: a slave asked twice back to "
        "back and silent for 2 x 0.1 s from the end of its first unanswered request "
        "is offline then, while the second request still waits (docs/POLLER.md, "
        '"Slave health"; each failed transaction costs the t3.5, the request, the '
        "timeout and the master's 20 ms settling pause, so waiting for the second's "
        "own timeout put it at about 0.223 s). The timer starts at the first "
        "failure's report minus the timeout, never before the request's real end: the "
        "master's lateness in reporting that timeout is the allowance of the check "
        "(plus 2 ms for the timer). Measured from the end of the first unanswered "
        "request on the wire (the master's own stamp) to the scheduler's offline event "
        "and to the bridge's. Before that request come the drive's end (its process "
        "handles SIGTERM) and the wait for its turn in the schedule.",
        "* Write: a client process publishes 200 commands 30 ms apart, each with its "
        "send time; the bridge notes when each write's answer arrived (the bus is "
        "polled flat out: a write waits for the transaction in progress, then goes "
        "ahead of the polls).",
        "",
        "",
    ]
    return "\n".join(L)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--updates", type=int, default=100_000)
    ap.add_argument("--only", default="throughput,wire,unplug,write,share,outage")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument(
        "--rounds",
        type=int,
        default=5,
        help="throughput: rounds of the bare loop and the bridge, alternately (the medians)",
    )
    ap.add_argument("--outage", type=float, default=30.0)
    ap.add_argument(
        "--runs",
        type=int,
        default=1,
        help="run the latency and unplugged scenarios this many times: the median of each figure",
    )
    ap.add_argument("--json", type=Path, help="also write the figures of this run here")
    ns = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        res: dict[str, Any] = {}
        if "throughput" in ns.only:
            res["throughput"] = throughput(tmp, ns.updates, ns.rounds)
        if "wire" in ns.only:
            res["wire"] = median_of([wire_and_latency(tmp, ns.seconds) for _ in range(ns.runs)])
            res["wire1"] = median_of([wire_and_latency(tmp, ns.seconds, 1) for _ in range(ns.runs)])
        if "unplug" in ns.only:
            res["unplug"] = median_of([unplugged(tmp, ns.seconds) for _ in range(ns.runs)])
        if "write" in ns.only:
            res["write"] = write_latency(tmp, 200)
        if "share" in ns.only:
            res["share"] = shared_subscription(tmp, ns.seconds)
        if "outage" in ns.only:
            res["outage"] = broker_outage(tmp, ns.outage)
            res["outage_s"] = ns.outage
        res["machine"] = {
            "started_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime(T0)),
            "duration_s": round(time.time() - T0),
            "load_avg_1m_before": LOAD0,
            "load_avg_1m_after": os.getloadavg()[0],
            "cpus": os.cpu_count(),
        }
        res["runs"] = ns.runs
        print(json.dumps(res, indent=1))
        if ns.json:
            ns.json.write_text(json.dumps(res, indent=1) + "\n")
        print(section(res, " ".join(["python bench/bench_bridge.py", *sys.argv[1:]])))


if __name__ == "__main__":
    main()
