"""The bridge's set round trip (issue 27.6): an MQTT client publishes a set command
and waits for the point's new value, read back from the drive, to arrive on the
point's topic; with and without TCP_NODELAY on the bridge's MQTT socket and on
mosquitto's (``set_tcp_nodelay true``).

    python bench/bench_set_roundtrip.py [--sets 200] [--json FILE]

Each variant starts its own mosquitto on a free loopback port (tests/mqtt_broker.py,
its configuration with or without ``set_tcp_nodelay``), a ``pyrtu vbus`` and a
simulated CV100 drive (``pyrtu simulate cv100``, address 5, 115200 baud), and the
bridge as a user runs it (``pyrtu bridge --config``, its own process; "off" for the
bridge replaces `MqttLink._socket_opened`, which sets the option, by a no-op).  The
client (paho-mqtt in this process, TCP_NODELAY on its own socket so that only the
bridge and the broker vary) publishes ``N`` sets of the CV100's main setting
(0x3201, QoS 1, a new value each, 20 ms after the previous value came) and times
each from the publish to the value's arrival.  bench/report.py runs it
(``--json``) for bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import socket
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

HEADING = "## Set round trip and TCP_NODELAY (issue 27.6)"
BAUD = 115200
TOPIC = "pyrtu/rt/b0/5/ref"

#: the bridge, with its MQTT socket's TCP_NODELAY left off ("before")
NAGLE_BRIDGE = (
    "import sys\n"
    "from pyrtu.bridge.mqtt import MqttLink\n"
    "MqttLink._socket_opened = lambda self, client, userdata, sock: None\n"
    "from pyrtu.cli import main\n"
    "sys.exit(main(sys.argv[1:]))\n"
)


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q / 100 * (len(s) - 1)))]


def config(url: str, path: str, outbox: Path) -> str:
    return (
        f'[mqtt]\nurl = "{url}"\nedge = "rt"\noutbox = "{outbox}"\nqos = 1\n'
        "write_rate = 1000\n\n"
        f'[[bus]]\nname = "b0"\nport = "{path}"\nbaudrate = {BAUD}\nparity = "N"\n'
        "timeout = 0.1\n\n"
        '[[point]]\nname = "ref"\nbus = "b0"\nslave = 5\ntable = "holding"\n'
        f"address = {0x3201}\nwritable = true\ninterval = 1\n"
    )


@contextlib.contextmanager
def bridge(cfg: Path, nodelay: bool) -> Iterator[subprocess.Popen[bytes]]:
    """``pyrtu bridge --config cfg`` (its stderr in bridge.log beside the config)."""
    argv = [sys.executable, "-m", "pyrtu"] if nodelay else [sys.executable, "-c", NAGLE_BRIDGE]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    with open(cfg.parent / "bridge.log", "wb") as log:
        proc = subprocess.Popen(
            [*argv, "bridge", "--config", str(cfg)], env=env, cwd=ROOT, stderr=log
        )
    try:
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


class Setter:
    """The MQTT client that sets and waits for the value."""

    def __init__(self, port: int) -> None:
        self.cond = threading.Condition()
        self.values: list[tuple[float, Any]] = []
        c = paho.Client(CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5)
        c.on_socket_open = lambda client, userdata, sock: sock.setsockopt(
            socket.IPPROTO_TCP, socket.TCP_NODELAY, 1
        )
        c.on_message = self._message
        c.connect("127.0.0.1", port, 30)
        c.subscribe(TOPIC, 1)
        c.loop_start()
        self.client = c

    def _message(self, client: Any, userdata: Any, msg: paho.MQTTMessage) -> None:
        now = time.perf_counter()
        doc = json.loads(msg.payload)
        with self.cond:
            self.values.append((now, doc.get("value")))
            self.cond.notify_all()

    def wait_value(self, value: int, since: int, patience: float = 5.0) -> float | None:
        """When ``value`` arrived among the values from index ``since`` on."""
        end = time.monotonic() + patience
        with self.cond:
            while True:
                for t, v in self.values[since:]:
                    if v == value:
                        return t
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(left)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def variant(
    tmp: Path, path: str, sets: int, bridge_nodelay: bool, broker_nodelay: bool
) -> dict[str, Any]:
    broker = Broker(tmp)
    if not broker_nodelay:
        text = broker.conf.read_text().replace("set_tcp_nodelay true\n", "")
        broker.conf.write_text(text)
    with broker:
        cfg = tmp / "bridge.toml"
        cfg.write_text(config(broker.url, path, tmp / f"outbox-{broker.port}"))
        setter = Setter(broker.port)
        try:
            with bridge(cfg, bridge_nodelay):
                end = time.monotonic() + 20
                while not setter.values and time.monotonic() < end:
                    time.sleep(0.05)  # the first value: the bridge is up
                if not setter.values:
                    raise RuntimeError("the bridge published no value")
                rtt: list[float] = []
                lost = 0
                for i in range(sets):
                    value = 1000 + (i % 2) * 7 + (i // 2) % 50
                    since = len(setter.values)
                    t0 = time.perf_counter()
                    setter.client.publish(f"{TOPIC}/set", str(value).encode(), 1)
                    t1 = setter.wait_value(value, since)
                    if t1 is None:
                        lost += 1
                    else:
                        rtt.append((t1 - t0) * 1e3)
                    time.sleep(0.02)
        finally:
            setter.close()
    return {
        "bridge_nodelay": bridge_nodelay,
        "broker_nodelay": broker_nodelay,
        "n": len(rtt),
        "lost": lost,
        "p50_ms": pct(rtt, 50),
        "p90_ms": pct(rtt, 90),
        "p99_ms": pct(rtt, 99),
        "mean_ms": statistics.fmean(rtt),
    }


def section(rows: list[dict[str, Any]], cmd: str) -> str:
    def onoff(b: bool) -> str:
        return "on" if b else "off"

    load = os.getloadavg()[0]
    lines = [
        HEADING,
        "",
        f"`{cmd}`, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
        f"load average {load:.1f} on {os.cpu_count()} cores.",
        "",
        "An MQTT client publishes a set of the CV100's main setting (QoS 1, a new value "
        "each time) and times it until the read-back value arrives on the point's topic "
        "(the bridge, `pyrtu bridge` in its own process; mosquitto and the simulated drive "
        "on a virtual bus at 115200 baud, all on loopback; the client's own socket has "
        "TCP_NODELAY in every row).",
        "",
        "| bridge TCP_NODELAY | mosquitto set_tcp_nodelay | sets | p50 ms | p90 ms | p99 ms |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lost = f" ({r['lost']} lost)" if r["lost"] else ""
        lines.append(
            f"| {onoff(r['bridge_nodelay'])} | {onoff(r['broker_nodelay'])} | {r['n']}{lost} | "
            f"{r['p50_ms']:.1f} | {r['p90_ms']:.1f} | {r['p99_ms']:.1f} |"
        )
    lines += [
        "",
        "The round trip includes the FC 06 write and the FC 03 read-back on the bus (two "
        "transactions at 115200 baud, about 2 ms) and the MQTT hops: client to broker, "
        "broker to bridge, bridge to broker, broker to client.  Without TCP_NODELAY a "
        "small packet that follows an unacknowledged one waits for the peer's delayed "
        "ACK (40 ms on Linux): pyrtu sets it on every TCP socket it opens or accepts "
        "(`pyrtu.tcp.sockets.set_nodelay`), and docs/BRIDGE.md tells users to set "
        "`set_tcp_nodelay true` in mosquitto.conf.  Either one off costs one delayed ACK "
        "on a hop; both off, two.  The figures include the scheduling of five processes "
        "(client, broker, bridge, hub, drive).  Issue 27 measured a p50 of 3.2 ms with "
        "both set; where this setup's remaining milliseconds go (the drive's turnaround, "
        "the outbox's fsync batch, the bridge's loop) is not yet broken down.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    import bench_client

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--sets", type=int, default=200, help="sets per variant (default 200)")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ns = ap.parse_args()
    variants = [(True, True), (False, False), (True, False), (False, True)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp, bench_client.vbus(BAUD) as (paths, _pid):
        with bench_client.drives([paths[1]], BAUD, "cv100"):
            for i, (bridge_on, broker_on) in enumerate(variants):
                d = Path(tmp) / f"v{i}"
                d.mkdir()
                r = variant(d, paths[0], ns.sets, bridge_on, broker_on)
                rows.append(r)
                print(json.dumps(r), flush=True)
    if ns.json:
        ns.json.write_text(json.dumps({"sets": ns.sets, "rows": rows}, indent=1) + "\n")
    cmd = "python bench/bench_set_roundtrip.py " + " ".join(sys.argv[1:])
    text = section(rows, cmd.strip())
    print(text)


if __name__ == "__main__":
    main()
