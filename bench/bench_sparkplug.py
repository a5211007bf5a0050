"""The Sparkplug B edge node's benchmark (issue 33's targets): a broker SIGKILLed
for 30 s with the primary host online throughout (values lost, published twice,
out of order per metric, against the values the simulated drive produced), the
time a Rebirth takes (NCMD published to the last DBIRTH received), a
10,000-metric DBIRTH published and decoded, and the node's throughput against
the JSON bridge's (QoS 0, the same 200 points, the same broker, alternate rounds).

    python bench/bench_sparkplug.py [--outage 30] [--rebirths 20] [--rounds 5] [--json FILE]

Every part starts its own mosquitto (tests/mqtt_broker.py); the drives are
simulated on the virtual bus; the host application is the tests'
(tests/sparkplug/sparkplug_host.py: its own protobuf decoder); the outage rig is
tests/sparkplug/outage.py's (the ground truth: what the drive served).
bench/report.py runs it (``--json``) for bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "tests" / "sparkplug"), str(BENCH)]

import bench_bridge  # noqa: E402
import test_sparkplug_node as node_tests  # noqa: E402
from mqtt_broker import Broker  # noqa: E402
from outage import WATCHED, Feeder, aliases, outage_rig, received, tally  # noqa: E402
from sparkplug_host import Host, decode, encode_metric, encode_payload  # noqa: E402

from pyrtu.drivers._loopthread import LoopThread  # noqa: E402
from pyrtu.drivers.aio import run as aio_run  # noqa: E402
from pyrtu.poller import Update  # noqa: E402
from pyrtu.sparkplug.config import load_sparkplug_config  # noqa: E402
from pyrtu.sparkplug.node import EdgeNode  # noqa: E402
from pyrtu.sparkplug.payload import payload_class  # noqa: E402

HEADING = "## Sparkplug B edge node (issue 33)"
REBIRTH = encode_payload(encode_metric(name="Node Control/Rebirth", value=True))


def pct(values: list[float], q: float) -> float:
    return bench_bridge.pct(values, q)


# ---------------------------------------------------------------------- broker outage


def outage(tmp: Path, seconds: float) -> dict[str, Any]:
    """The drive's values change (each held until read twice); the broker is
    SIGKILLed, stays down ``seconds``, starts again; values go on changing 3 s; the
    host (online throughout: it connects again and says so) must have every value
    once, in order, live or historical."""
    with outage_rig(tmp) as rig:
        feeder = Feeder(rig.sim, patience=max(60.0, 2 * seconds))
        feeder.start()
        try:
            time.sleep(3.0)
            births = len(rig.host.of("DBIRTH", "weg"))
            rig.broker.kill()
            killed = time.monotonic()
            time.sleep(seconds)
            rig.broker.start()
            back = time.monotonic()
            rig.host.wait(lambda: len(rig.host.of("DBIRTH", "weg")) > births, "births", 60)
            reborn = time.monotonic() - back
            time.sleep(3.0)
        finally:
            feeder.stop()
        al = aliases(rig.host)
        give_up = time.monotonic() + 60
        for name, _reg, dt in WATCHED:
            last = feeder.produced[name][-1]
            while last not in [v for v, _h in received(rig.host, al[name], dt)]:
                if time.monotonic() > give_up:
                    break
                time.sleep(0.02)
        time.sleep(1.0)
        stats = rig.node.stats()
        per_metric = {
            name: tally(feeder.produced[name], received(rig.host, al[name], dt))
            for name, _reg, dt in WATCHED
        }
    return {
        "outage_s": seconds,
        "down_s": back - killed,
        "births_after_restart_s": reborn,
        "per_metric": per_metric,
        "connects": stats["connects"],
        "metrics_historical": stats["metrics_historical"],
        "metrics_live": stats["metrics_live"],
    }


# ---------------------------------------------------------------------- rebirth


def rebirths(tmp: Path, n: int) -> dict[str, Any]:
    """``n`` Rebirth commands, one at a time, to the node of the tests' rig (a
    CFW701 and a CV100: two DBIRTHs): the time from publishing the NCMD to the
    receipt of the last DBIRTH at the host; the births' sizes."""
    times: list[float] = []
    with node_tests.rig(tmp) as r:
        host = r.host
        host.wait(lambda: node_tests.dbirthed(host, "weg", "cv"), "the births")
        ncmd = f"spBv1.0/{node_tests.GROUP}/NCMD/{node_tests.EDGE}"
        time.sleep(0.5)
        for _ in range(n):
            before = len(host.of("DBIRTH"))
            t0 = time.monotonic()
            host.command(ncmd, REBIRTH)
            host.wait(lambda b=before: len(host.of("DBIRTH")) >= b + 2, "the DBIRTHs")
            last = host.of("DBIRTH")[before + 1]
            times.append(last.arrived - t0)
            time.sleep(0.2)
        nbirth = len(host.of("NBIRTH")[-1].payload)
        dbirths = [len(m.payload) for m in host.of("DBIRTH")[-2:]]
    ms = [1e3 * t for t in times]
    return {
        "n": n,
        "ms": {"p50": statistics.median(ms), "p95": pct(ms, 95), "max": max(ms)},
        "nbirth_bytes": nbirth,
        "dbirth_bytes": dbirths,
    }


def big_dbirth(tmp: Path, metrics: int = 10_000) -> dict[str, Any]:
    """An edge node with one device of ``metrics`` points (no polling): its DBIRTH
    published at connect, received by the host and decoded (the host's own
    decoder, and protobuf's); a Rebirth of it timed as above."""
    points = "".join(
        f'[[point]]\nname = "m{i}"\nbus = "line"\nslave = 9\ntable = "holding"\naddress = {i}\n'
        for i in range(metrics)
    )
    with Broker(tmp) as broker:
        path = tmp / "big.toml"
        path.write_text(
            f'[mqtt]\nurl = "{broker.url}"\nedge = "big"\noutbox = "{tmp / "ob-big"}"\n\n'
            '[sparkplug]\ngroup_id = "bench"\n\n'
            '[[bus]]\nname = "line"\nport = "/dev/null"\nbaudrate = 115200\n\n' + points
        )
        t0 = time.perf_counter()
        cfg = load_sparkplug_config(path)
        load_s = time.perf_counter() - t0
        host = Host(broker)
        node = EdgeNode(cfg)
        thread = LoopThread("big", lambda: node.start(poll=False), node.stop)
        t1 = time.monotonic()
        thread.start()
        try:
            host.wait(lambda: host.of("DBIRTH"), "the DBIRTH", 120)
            first = host.of("DBIRTH")[0]
            start_to_dbirth = first.arrived - t1
            t2 = time.perf_counter()
            mine = decode(first.payload)
            host_decode = time.perf_counter() - t2
            t3 = time.perf_counter()
            pb = payload_class().FromString(first.payload)
            pb_decode = time.perf_counter() - t3
            assert len(mine.metrics) == metrics == len(pb.metrics)
            assert [m.name for m in mine.metrics] == [f"m{i}" for i in range(metrics)]
            times = []
            for _ in range(5):
                before = len(host.of("DBIRTH"))
                t4 = time.monotonic()
                host.command("spBv1.0/bench/NCMD/big", REBIRTH)
                host.wait(lambda b=before: len(host.of("DBIRTH")) > b, "the DBIRTH", 60)
                times.append(host.of("DBIRTH")[before].arrived - t4)
                time.sleep(0.2)
            session_build = timed_dbirth(node)
        finally:
            thread.stop()
            host.close()
    return {
        "metrics": metrics,
        "bytes": len(first.payload),
        "config_load_s": load_s,
        "start_to_dbirth_s": start_to_dbirth,
        "build_ms": 1e3 * session_build,
        "host_decode_ms": 1e3 * host_decode,
        "protobuf_decode_ms": 1e3 * pb_decode,
        "rebirth_ms": {"p50": 1e3 * statistics.median(times), "max": 1e3 * max(times)},
    }


def timed_dbirth(node: EdgeNode) -> float:
    """Seconds to build (serialize) the device's DBIRTH once, the median of 5."""
    (dev,) = node.spb.devices
    runs = []
    for _ in range(5):
        t = time.perf_counter()
        node.session.dbirth(dev, {}, time.time())
        runs.append(time.perf_counter() - t)
    return statistics.median(runs)


# ---------------------------------------------------------------------- throughput


def node_rate(url: str, tmp: Path, n: int) -> dict[str, float]:
    """``n`` updates of the JSON benchmark's 200 points (4 devices of 50) fed to an
    edge node (reporter, outbox, DDATA) as fast as the broker confirms them;
    updates per second confirmed (the outbox's cursor past the last one)."""
    text = bench_bridge._config(url, tmp / f"ob-spb-{time.time_ns()}", 0)
    text = text.replace("[[bus]]", '[sparkplug]\ngroup_id = "bench"\n\n[[bus]]', 1)
    path = tmp / f"spb-{time.time_ns()}.toml"
    path.write_text(text)
    cfg = load_sparkplug_config(path)
    pts = bench_bridge._points(200)

    async def main() -> dict[str, float]:
        node = EdgeNode(cfg)
        await node.start(poll=False)
        while not node.stats()["born"]:
            await asyncio.sleep(0.01)
        ob = node._outbox
        assert ob is not None
        first = ob.next_seq
        t0, c0 = time.perf_counter(), time.process_time()
        i = 0
        while i < n:
            if ob.depth > 4000:
                await asyncio.sleep(0)
                continue
            for _ in range(100):
                node.feed(Update(pts[i % 200], i, time.time()))
                i += 1
            await asyncio.sleep(0)
        last = first + n - 1
        while ob.acked < last:
            await asyncio.sleep(0.001)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        sent = node.counts["metrics_live"] + node.counts["metrics_historical"]
        await node.stop()
        return {"per_s": n / wall, "cpu_us": 1e6 * cpu / n, "metrics_sent": sent}

    return dict(aio_run(main()))


def json_rate(url: str, tmp: Path, n: int) -> dict[str, float]:
    """The JSON bridge's, as bench_bridge.bridge_rate at QoS 0 (acknowledged: written)."""
    return bench_bridge.bridge_rate(url, tmp, 0, n)


def throughput(tmp: Path, n: int, rounds: int) -> dict[str, Any]:
    ours, theirs = [], []
    load = [os.getloadavg()[0]]
    with Broker(tmp) as broker:
        for _ in range(rounds):
            theirs.append(json_rate(broker.url, tmp, n))
            ours.append(node_rate(broker.url, tmp, n))
    load.append(os.getloadavg()[0])
    o = statistics.median(r["per_s"] for r in ours)
    j = statistics.median(r["per_s"] for r in theirs)
    return {
        "updates": n,
        "rounds": rounds,
        "sparkplug": {
            "per_s": o,
            "cpu_us": statistics.median(r["cpu_us"] for r in ours),
            "rounds": [round(r["per_s"]) for r in ours],
        },
        "json": {
            "per_s": j,
            "cpu_us": statistics.median(r["cpu_us"] for r in theirs),
            "rounds": [round(r["per_s"]) for r in theirs],
        },
        "ratio": o / j,
        "round_ratios": [
            round(a["per_s"] / b["per_s"], 3) for a, b in zip(ours, theirs, strict=True)
        ],
        "load_avg_1m": load,
    }


# ---------------------------------------------------------------------- main


def summary(r: dict[str, Any]) -> str:
    out = [HEADING, ""]
    if "outage" in r:
        o = r["outage"]
        out.append(f"broker killed for {o['outage_s']:g} s (down {o['down_s']:.1f} s):")
        for name, t in o["per_metric"].items():
            out.append(f"  {name}: {json.dumps(t)}")
    if "rebirth" in r:
        rb = r["rebirth"]
        out.append(f"rebirth (NCMD to the last DBIRTH, {rb['n']}x): {json.dumps(rb['ms'])} ms, "
                   f"NBIRTH {rb['nbirth_bytes']} B, DBIRTHs {rb['dbirth_bytes']} B")  # fmt: skip
    if "big" in r:
        out.append(f"10,000-metric DBIRTH: {json.dumps(r['big'])}")
    if "throughput" in r:
        t = r["throughput"]
        out.append(f"throughput QoS 0: sparkplug {t['sparkplug']['per_s']:.0f}/s, json "
                   f"{t['json']['per_s']:.0f}/s, ratio {t['ratio']:.2f}")  # fmt: skip
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--outage", type=float, default=30.0, help="seconds the broker is down")
    ap.add_argument("--rebirths", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=5, help="throughput rounds")
    ap.add_argument("--updates", type=int, default=20_000, help="updates per throughput round")
    ap.add_argument("--only", help="comma-separated: outage,rebirth,big,throughput")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    parts = args.only.split(",") if args.only else ["throughput", "rebirth", "big", "outage"]
    result: dict[str, Any] = {"load_avg_1m_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory(prefix="bench-spb-") as d:
        tmp = Path(d)
        for part in parts:
            sub = tmp / part
            sub.mkdir()
            if part == "outage":
                result["outage"] = outage(sub, args.outage)
            elif part == "rebirth":
                result["rebirth"] = rebirths(sub, args.rebirths)
            elif part == "big":
                result["big"] = big_dbirth(sub)
            elif part == "throughput":
                result["throughput"] = throughput(sub, args.updates, args.rounds)
            else:
                ap.error(f"--only: unknown part {part!r}")
    result["load_avg_1m_end"] = os.getloadavg()[0]
    print(summary(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
