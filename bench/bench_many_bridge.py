"""A thousand Modbus TCP devices whose values change, through ``pyrtu bridge`` into
mosquitto (issue 30: "1,000 simulated TCP devices x 30 registers at 1 Hz ... With
the bridge publishing every change to mosquitto: 30,000 points/s on at most one
core").

    python bench/bench_many_bridge.py [--devices 1000] [--registers 30]
        [--seconds 20] [--warmup 8] [--vary 0.5] [--quick]
        [--kinds json,json-device,sparkplug] [--json FILE]

Four processes, each its own: the devices, one ``pyrtu simulate --template T
--tcp 127.0.0.1:FIRST-LAST --vary 0.5`` (a device of ``--registers`` holding
registers on every port of the range, none writable: every one of them takes the
next value of its ramp, one count up, every half second, so that every poll, one
a second, reads a changed value: with ``--vary 1`` the polls and the steps have
the same period in phases of their own, and a poll that falls within its jitter
of a step reads one step twice and misses the next, about 1 % of them here:
fewer changes to publish than 30,000/s); a mosquitto started here on a
free loopback port (tests/mqtt_broker.py: a generated configuration, stopped
by pid); ``pyrtu bridge --config FILE`` with one ``tcp://``
bus per device, each device's registers as points polled every second, published
on change (report by exception, no deadband, QoS 1, the durable outbox: the
defaults of ``[mqtt]``); and a ``mosquitto_sub`` (C) subscribed to the values,
writing each message's receipt time (and payload) to a file.

``json`` is the bridge's JSON topics (a message per point); ``json-device`` the
same with ``messages = "device"`` in ``[mqtt]``: one message per device per poll,
``{"points": {NAME: {"value", "time", "quality", "seq"}}}`` on
``pyrtu/bench/{bus}/1/values`` (decoded here with the json module); ``sparkplug``
the same configuration with a ``[sparkplug]`` table: the Sparkplug B edge node,
whose DDATA messages carry a device's changed points as metrics (decoded here by
the tests' own decoder, tests/sparkplug/sparkplug_host.py, no code of pyrtu).

After the first value arrives and ``--warmup`` seconds more (every device
connected and polled), the script measures over ``--seconds``:

* points published per second: the value messages (JSON), the points of the
  device messages (JSON device messages) or DDATA metrics (Sparkplug) the
  subscriber received with a receipt time in the window, counted
  by the subscriber, not by the bridge (mosquitto's ``$SYS`` count of the PUBLISH
  packets it received leaves out retained ones, the JSON bridge's values);
* whether every change was published: every point published about once a
  second (the points published in the window, the fewest and most messages of
  one), and each point's consecutive published values at most three steps apart
  (a poll a second reads two steps on, one or three when a step falls within
  its jitter; more is a poll's change not published, or a poll late by half a
  second);
* the CPU (user + system, /proc/PID/stat) of the bridge, mosquitto and the
  simulator over the wall time, in % of one core, and the bridge's per point
  published (its poller's share included); the bridge's resident memory
  (``VmRSS``) at the middle and at the end of the window.

The machine's load average is taken before and after.  bench/report.py runs it
(``--json``) for bench/RESULTS.md; the summary goes to stdout.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "tests" / "sparkplug")]

from bench_many_devices import (  # noqa: E402
    child_env,
    proc_cpu,
    rss_kib,
    start_devices,
    template_text,
)
from mqtt_broker import Broker  # noqa: E402
from sparkplug_host import decode  # noqa: E402

TIMEOUT = 1.0  # each bus's timeout
EDGE = "bench"
GROUP = "bench"
VARY = 0.5  # the simulator's step (--vary), s: two a poll
INTERVAL = 1.0  # every point's poll interval, s
KINDS = ("json", "json-device", "sparkplug")


def config_text(url: str, outbox: Path, first: int, devices: int, registers: int, kind: str) -> str:
    """The bridge's configuration: one ``tcp://`` bus per device, its registers as
    points polled every second (``kind`` json-device: a message per device per poll;
    sparkplug: with a ``[sparkplug]`` table)."""
    out = [f'[mqtt]\nurl = "{url}"\nedge = "{EDGE}"\noutbox = "{outbox}"\n']
    if kind == "json-device":
        out.append('messages = "device"\n')
    if kind == "sparkplug":
        out.append(f'[sparkplug]\ngroup_id = "{GROUP}"\n')
    out.append(f'[defaults]\ninterval = {INTERVAL}\ntable = "holding"\nslave = 1\n')
    for i in range(devices):
        port = first + i
        out.append(
            f'[[bus]]\nname = "d{i}"\nport = "tcp://127.0.0.1:{port}"\ntimeout = {TIMEOUT}\n'
        )
        for r in range(registers):
            out.append(f'[[point]]\nname = "d{i}.r{r}"\nbus = "d{i}"\naddress = {r}\n')
    return "\n".join(out)


def stop(proc: subprocess.Popen[Any], timeout: float = 30) -> None:
    """SIGTERM by pid, SIGKILL after ``timeout``."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(5)


@contextlib.contextmanager
def subscriber(port: int, topic: str, out: Path, fmt: str) -> Iterator[subprocess.Popen[bytes]]:
    """mosquitto_sub (C, its own process, QoS 1) writing one ``fmt`` line per message."""
    cmd = [shutil.which("mosquitto_sub") or "mosquitto_sub", "-h", "127.0.0.1",
           "-p", str(port), "-q", "1", "-t", topic, "-F", fmt]  # fmt: skip
    with open(out, "w") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.DEVNULL)
    try:
        yield proc
    finally:
        stop(proc, 5)


def lines_of(path: Path) -> int:
    with open(path, "rb") as f:
        return sum(1 for _ in f)


def json_points(path: Path, t0: float, t1: float) -> tuple[int, dict[str, list[int]]]:
    """The value messages received in the window (``%U %t %p`` lines) and each
    topic's values, in order."""
    count = 0
    values: dict[str, list[int]] = {}
    with open(path) as f:
        for line in f:
            t, topic, body = line.rstrip("\n").split(" ", 2)
            if not t0 <= float(t) < t1 or not body.startswith("{"):
                continue  # a slave's status (online), not a value
            count += 1
            doc = json.loads(body)
            values.setdefault(topic, []).append(doc["value"])
    return count, values


def device_points(path: Path, t0: float, t1: float) -> tuple[int, int, dict[str, list[int]]]:
    """The device messages and their points received in the window (``%U %t %p``
    lines), and each point's values, in order (by point name; a point twice in a
    message, or a message without points, is an error)."""
    messages = points = 0
    values: dict[str, list[int]] = {}
    with open(path) as f:
        for line in f:
            t, topic, body = line.rstrip("\n").split(" ", 2)
            if not t0 <= float(t) < t1:
                continue
            messages += 1
            pairs = json.loads(body, object_pairs_hook=list)[0][1]
            names = [name for name, _ in pairs]
            if not names or len(set(names)) != len(names):
                raise RuntimeError(f"{topic}: a message without points or a point twice: {body}")
            for name, doc in pairs:
                points += 1
                values.setdefault(name, []).append(dict(doc)["value"])
    return messages, points, values


def sparkplug_points(path: Path, t0: float, t1: float) -> tuple[int, int, dict[str, list[int]]]:
    """The DDATA messages and their metrics received in the window (``%U %t %x``
    lines), and each metric's values, in order (by device topic and alias)."""
    messages = metrics = 0
    values: dict[str, list[int]] = {}
    with open(path) as f:
        for line in f:
            t, topic, hexed = line.rstrip("\n").split(" ", 2)
            if not t0 <= float(t) < t1:
                continue
            messages += 1
            payload = decode(bytes.fromhex(hexed))
            for m in payload.metrics:
                metrics += 1
                key = f"{topic}/{m.alias if m.name is None else m.name}"
                values.setdefault(key, []).append(int(m.raw))
    return messages, metrics, values


def step_gaps(values: dict[str, list[int]], vary: float) -> dict[str, Any]:
    """Each point's consecutive published values (uint16 counts, wrapping): how many
    pairs, how many further apart than a poll's steps and a step of jitter, the
    largest; and the fewest and most values of one point."""
    pairs = far = largest = 0
    most_per_poll = round(INTERVAL / vary) + 1
    for seq in values.values():
        for a, b in itertools.pairwise(seq):
            d = (b - a) % 65536
            pairs += 1
            largest = max(largest, d)
            if d == 0 or d > most_per_poll:
                far += 1
    counts = [len(v) for v in values.values()]
    return {"pairs": pairs, "far_apart": far, "largest_step": largest,
            "fewest": min(counts, default=0), "most": max(counts, default=0)}  # fmt: skip


def run(kind: str, args: argparse.Namespace, sim: subprocess.Popen[str], first: int,
        tmp: Path) -> dict[str, Any]:  # fmt: skip
    """One bridge (``kind``) over the devices: what was measured."""
    work = tmp / kind
    work.mkdir()
    broker = Broker(work)
    broker.start()
    values_out, bridge_err = work / "values.txt", work / "bridge.err"
    config = work / "bridge.toml"
    config.write_text(config_text(broker.url, work / "outbox", first, args.devices,
                                  args.registers, kind))  # fmt: skip
    topic, fmt = {
        "json": (f"pyrtu/{EDGE}/+/+/+", "%U %t %p"),
        "json-device": (f"pyrtu/{EDGE}/+/+/values", "%U %t %p"),
        "sparkplug": (f"spBv1.0/{GROUP}/DDATA/{EDGE}/+", "%U %t %x"),
    }[kind]
    assert broker.proc is not None
    try:
        with subscriber(broker.port, topic, values_out, fmt):
            time.sleep(0.5)  # the subscriptions in place
            with open(bridge_err, "w") as err:
                bridge = subprocess.Popen(
                    [sys.executable, "-m", "pyrtu", "bridge", "--config", str(config)],
                    stdout=subprocess.DEVNULL, stderr=err, env=child_env(),
                )  # fmt: skip
            try:
                started = time.monotonic()
                while lines_of(values_out) == 0:
                    if bridge.poll() is not None or time.monotonic() > started + 120:
                        raise RuntimeError(
                            f"no value from the bridge: {bridge_err.read_text()[-2000:]}"
                        )
                    time.sleep(0.2)
                first_value = time.monotonic() - started
                time.sleep(args.warmup)
                load0 = os.getloadavg()[0]
                pids = {"bridge": bridge.pid, "mosquitto": broker.proc.pid, "simulator": sim.pid}
                cpu0 = {k: proc_cpu(p) for k, p in pids.items()}
                t0, m0 = time.time(), time.monotonic()
                time.sleep(args.seconds / 2)
                rss_mid = rss_kib(bridge.pid)
                time.sleep(args.seconds / 2)
                t1, m1 = time.time(), time.monotonic()
                cpu1 = {k: proc_cpu(p) for k, p in pids.items()}
                rss_end = rss_kib(bridge.pid)
                load1 = os.getloadavg()[0]
                time.sleep(1.0)  # the window's last messages written
            finally:
                stop(bridge)
    finally:
        broker.stop()
    wall = m1 - m0
    result: dict[str, Any] = {
        "seconds": wall,
        "first_value_s": first_value,
        "cpu_pct": {k: 100.0 * (cpu1[k] - cpu0[k]) / wall for k in pids},
        "rss_mid_kib": rss_mid,
        "rss_end_kib": rss_end,
        "load_avg_1m_before": load0,
        "load_avg_1m_after": load1,
        "bridge_exit": bridge.returncode,
    }
    if kind == "json":
        count, values = json_points(values_out, t0, t1)
        result["messages_per_s"] = count / (t1 - t0)
        result["points_per_s"] = count / (t1 - t0)
    elif kind == "json-device":
        messages, points, values = device_points(values_out, t0, t1)
        result["messages_per_s"] = messages / (t1 - t0)
        result["points_per_s"] = points / (t1 - t0)
    else:
        messages, metrics, values = sparkplug_points(values_out, t0, t1)
        result["messages_per_s"] = messages / (t1 - t0)
        result["points_per_s"] = metrics / (t1 - t0)
    # the bridge's CPU per point published (the poller's share included)
    result["bridge_us_per_point"] = (
        1e4 * result["cpu_pct"]["bridge"] / max(result["points_per_s"], 1e-9)
    )
    result["points_seen"] = len(values)
    result["steps"] = step_gaps(values, args.vary)
    result["offered_per_s"] = args.devices * args.registers / INTERVAL
    return result


def measure(args: argparse.Namespace) -> dict[str, Any]:
    with contextlib.ExitStack() as stack:
        tmp = args.keep or Path(
            stack.enter_context(tempfile.TemporaryDirectory(prefix="pyrtu-mb-"))
        )
        tmp.mkdir(parents=True, exist_ok=True)
        template = tmp / "many.toml"
        template.write_text(template_text(args.registers))
        sim, first = start_devices(template, args.devices, "--vary", f"{args.vary:g}")
        try:
            runs = {}
            for kind in args.kinds:
                print(f"bench_many_bridge: {kind}, {args.devices} devices", flush=True)
                runs[kind] = run(kind, args, sim, first, tmp)
        finally:
            stop(sim)
    return runs


def summary(doc: dict[str, Any]) -> str:
    lines = [
        f"{doc['devices']} devices x {doc['registers']} registers stepping every "
        f"{doc['vary']:g} s, polled at {1 / INTERVAL:g} Hz, {doc['seconds']:g} s measured"
    ]
    for kind, r in doc["runs"].items():
        cpu, st = r["cpu_pct"], r["steps"]
        per = {"json": "message", "json-device": "device message"}.get(kind, "DDATA")
        lines.append(
            f"{kind:11} {r['points_per_s']:8,.0f} points/s ({r['messages_per_s']:,.0f} "
            f"{per}s/s) of {r['offered_per_s']:,.0f} "
            f"offered; CPU bridge {cpu['bridge']:.0f} %, mosquitto {cpu['mosquitto']:.0f} %, "
            f"simulator {cpu['simulator']:.0f} % of a core "
            f"({r['bridge_us_per_point']:.0f} µs of the bridge's CPU per point); bridge RSS "
            f"{r['rss_end_kib'] / 1024:.0f} MiB; {r['points_seen']:,} points published "
            f"({st['fewest']}..{st['most']} values each), {st['far_apart']} of "
            f"{st['pairs']:,} consecutive values too far apart (largest "
            f"{st['largest_step']} steps); load {r['load_avg_1m_before']:.2f} -> "
            f"{r['load_avg_1m_after']:.2f}"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=1000)
    ap.add_argument("--registers", type=int, default=30)
    ap.add_argument("--seconds", type=float, default=20.0, help="measured, per run")
    ap.add_argument("--warmup", type=float, default=8.0, help="after the first value, per run")
    ap.add_argument("--vary", type=float, default=VARY, help="the simulator's --vary, s")
    ap.add_argument("--keep", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--quick", action="store_true", help="--seconds 8 --warmup 5")
    ap.add_argument("--kinds", default=",".join(KINDS), help=f"of {', '.join(KINDS)}")
    ap.add_argument("--json", type=Path, default=None, help="also save the figures here")
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.warmup = 8.0, 5.0
    args.kinds = args.kinds.split(",")
    if any(k not in KINDS for k in args.kinds):
        ap.error(f"--kinds: {', '.join(KINDS)}, not {','.join(args.kinds)!r}")
    runs = measure(args)
    doc = {
        "command": shlex.join(["python", "bench/bench_many_bridge.py", *sys.argv[1:]]),
        "devices": args.devices,
        "registers": args.registers,
        "seconds": args.seconds,
        "warmup": args.warmup,
        "vary": args.vary,
        "interval": INTERVAL,
        "cpus": os.cpu_count(),
        "runs": runs,
    }
    print(summary(doc))
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
