"""The broker-outage rig of the Sparkplug edge node (tests/sparkplug/test_sparkplug_outage.py
and bench/bench_sparkplug.py): a simulated CFW701 on the virtual bus whose values a
`Feeder` changes, each change held until the drive has answered two reads of it
(the ground truth is what the drive served, not what the node says it read);
mosquitto; the node with a primary host; the host application
(sparkplug_host.py) that publishes its STATE again on every connection.

`tally` compares, per metric, the values the drive produced with the values the
host received in DDATA (live or historical): lost, received twice, out of order."""

from __future__ import annotations

import contextlib
import itertools
import struct
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge_configs import BAUD
from mqtt_broker import Broker
from sparkplug_host import DT, Host
from test_sparkplug_node import config
from waiting import ANSWER_TIMEOUT

from pyrtu.devices import CFW701Simulator, weg
from pyrtu.drivers._loopthread import LoopThread
from pyrtu.sparkplug.config import load_sparkplug_config
from pyrtu.sparkplug.node import EdgeNode

vbus: Any
try:
    import pyrtu.vbus as vbus
except ImportError:  # pragma: no cover - the callers skip first
    vbus = None

#: the metrics the feeder changes: (metric name, register, datatype)
WATCHED = (("accel", weg.P_ACCEL_TIME, DT["UInt16"]), ("decel", weg.P_DECEL_TIME, DT["Int16"]))


class CountingCFW701(CFW701Simulator):
    """A CFW701 that counts the reads (FC 03/04) covering each watched register."""

    def __init__(self) -> None:
        super().__init__()
        self.reads = {reg: 0 for _name, reg, _dt in WATCHED}

    def _on_telegram(self, now: float, unit: int, pdu: bytes) -> None:
        super()._on_telegram(now, unit, pdu)
        if len(pdu) >= 5 and pdu[0] in (3, 4):
            start, count = struct.unpack(">HH", pdu[1:5])
            for reg in self.reads:
                if start <= reg < start + count:
                    self.reads[reg] += 1


class Feeder:
    """Changes every watched register (10001, 10002...: no drive's own value) on a
    thread of its own, the next change once the drive has served two reads of each
    register since the last."""

    def __init__(self, sim: CountingCFW701, patience: float = 30.0) -> None:
        self.sim = sim
        self.produced: dict[str, list[int]] = {name: [] for name, _r, _d in WATCHED}
        self.error: BaseException | None = None
        self.patience = patience
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="feeder", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        try:
            k = 0
            while not self._stop.is_set():
                k += 1
                value = 10000 + k % 20000
                reads = {}
                with self.sim.lock:
                    for name, reg, _dt in WATCHED:
                        self.sim.set(reg, value)
                        self.produced[name].append(value)
                    reads = dict(self.sim.reads)
                give_up = time.monotonic() + self.patience
                while any(self.sim.reads[r] < reads[r] + 2 for r in reads):
                    if time.monotonic() > give_up:
                        raise TimeoutError(f"the drive was not read for {self.patience} s")
                    time.sleep(0.002)
        except BaseException as e:  # reported by stop()
            self.error = e

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(60)
        if self.error is not None:
            raise self.error


@dataclass
class OutageRig:
    broker: Broker
    sim: CountingCFW701
    node: EdgeNode
    host: Host


class StatefulHost(Host):
    """The host application, publishing its STATE online again after every
    (re)connection and subscription, as a primary host does."""

    def __init__(self, broker: Broker) -> None:
        super().__init__(broker)
        self.client.reconnect_delay_set(0.05, 0.2)
        self.client.on_subscribe = self._resubscribed

    def _resubscribed(self, *args: object) -> None:
        self.subscriptions += 1
        threading.Thread(target=self.state, args=(True,), daemon=True).start()


@contextlib.contextmanager
def outage_rig(tmp: Path, interval: float = 0.02) -> Iterator[OutageRig]:
    """The node (primary host "scada") polling the counting CFW701 every
    ``interval`` s, a broker and the host, the host online and the births done."""
    with Broker(tmp) as broker, vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CountingCFW701()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        text = config(broker.url, bus.paths[0], tmp / "ob", 'primary_host_id = "scada"')
        text = text.replace("interval = 0.05", f"interval = {interval}")
        # the test is about the broker: a slave declared offline under a loaded
        # machine (DDEATH, DBIRTH) would republish its unchanged values, live
        text = text.replace("timeout = 0.1", f"timeout = {ANSWER_TIMEOUT}")
        # one drive: the CV100 of the shared configuration is left out
        head, _sep, rest = text.partition('[[device]]\nbus = "line"\nslave = 5')
        text = head + rest.partition("\n\n")[2]
        path = tmp / "b.toml"
        path.write_text(text)
        node = EdgeNode(load_sparkplug_config(path))
        thread = LoopThread("node", node.start, node.stop)
        thread.start()
        host = StatefulHost(broker)
        try:
            host.state(True)
            host.wait(lambda: host.of("DBIRTH", "weg"), "the DBIRTH")
            yield OutageRig(broker, sim, node, host)
        finally:
            thread.stop()
            host.close()
            sim.close()


def aliases(host: Host) -> dict[str, int]:
    birth = host.of("DBIRTH", "weg")[-1].decoded()
    return {m.name: m.alias for m in birth.metrics if m.name and m.alias is not None}


def received(host: Host, alias: int, datatype: int) -> list[tuple[int, bool]]:
    """(value, historical) of every DDATA metric ``alias``, in arrival order."""
    out = []
    for msg in host.of("DDATA", "weg"):
        for m in msg.decoded().metrics:
            if m.alias == alias:
                out.append((m.value(datatype), m.is_historical))
    return out


def tally(produced: list[int], got: list[tuple[int, bool]]) -> dict[str, int]:
    """Values produced and lost, received twice (``twice_live``: of those, a repeat
    not marked historical), received out of order; received live and historical.
    The produced values are distinct (a counter); a value the host had before the
    feeder began (``got`` not in ``produced``) is left out."""
    want = set(produced)
    values = [v for v, _h in got if v in want]
    seen: set[int] = set()
    twice = twice_live = 0
    for v, historical in got:
        if v not in want:
            continue
        if v in seen:
            twice += 1
            twice_live += not historical  # a repeat that is not a republished record
        seen.add(v)
    position = {v: i for i, v in enumerate(produced)}
    first = [position[v] for v in dict.fromkeys(values)]
    out_of_order = sum(1 for a, b in itertools.pairwise(first) if b < a)
    return {
        "produced": len(produced),
        "lost": len(want - seen),
        "twice": twice,
        "twice_live": twice_live,
        "out_of_order": out_of_order,
        "live": sum(1 for v, h in got if v in want and not h),
        "historical": sum(1 for v, h in got if v in want and h),
    }


def wait_delivered(rig: OutageRig, feeder: Feeder, patience: float = 60.0) -> None:
    """Until the host has the last value of every watched metric (or ``patience``)."""
    al = aliases(rig.host)
    give_up = time.monotonic() + patience
    for name, _reg, dt in WATCHED:
        last = feeder.produced[name][-1]
        while last not in [v for v, _h in received(rig.host, al[name], dt)]:
            if time.monotonic() > give_up:
                return
            time.sleep(0.02)


__all__ = [
    "WATCHED",
    "CountingCFW701",
    "Feeder",
    "OutageRig",
    "StatefulHost",
    "aliases",
    "outage_rig",
    "received",
    "tally",
    "wait_delivered",
]
