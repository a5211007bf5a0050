"""The Sparkplug B edge node (`pyrtu bridge` with ``[sparkplug]``) against a real
mosquitto and simulated drives on the virtual bus, judged by a host application
written from the specification (sparkplug_host.py: its own protobuf decoder).

Each test names the tck-id statements of the specification it checks
(docs/sparkplug.md's conformance table points here)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from bridge_configs import BAUD, OUTAGE, drives, mqtt_table, weg_on_line
from mqtt_broker import Broker
from sparkplug_host import DT, Host, Message, encode_metric, encode_payload

pytest.importorskip("google.protobuf", reason="protobuf is not installed (pyrtu[sparkplug])")

from pyrtu.devices import CFW701Simulator, CV100Simulator, weg
from pyrtu.drivers._loopthread import LoopThread
from pyrtu.sparkplug.config import load_sparkplug_config
from pyrtu.sparkplug.node import EdgeNode

GROUP, EDGE = "plant1", "e1"
ACCEL, DECEL = weg.P_ACCEL_TIME, weg.P_DECEL_TIME


def config(url: str, port: str, outbox: Path, sparkplug: str = "") -> str:
    more = "command_expiry = 5\nfsync_interval = 0.05\n"
    return f"""
{mqtt_table(url, outbox, more, EDGE)}
[sparkplug]
group_id = "{GROUP}"
{sparkplug}

{weg_on_line(port, 0.05, OUTAGE)}
[[device]]
bus = "line"
slave = 5
profile = "cv100"
name = "cv"
interval = 0.05

[[point]]
name = "weg.ref"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_REFERENCE}
writable = true
min = 0
max = 8192
unit = "rpm"
interval = 0.05

[[point]]
name = "weg.accel"
bus = "line"
slave = 1
table = "holding"
address = {ACCEL}
interval = 0.05

[[point]]
name = "weg.decel"
bus = "line"
slave = 1
table = "holding"
address = {DECEL}
type = "int16"
writable = true
interval = 0.05
"""


class Rig:
    def __init__(self, broker: Broker, bus: object, weg_sim: CFW701Simulator, node: EdgeNode,
                 host: Host, path: Path) -> None:  # fmt: skip
        self.broker, self.bus, self.weg, self.node, self.host, self.path = (
            broker, bus, weg_sim, node, host, path)  # fmt: skip
        self.sims: list[object] = []


@contextlib.contextmanager
def rig(tmp: Path, sparkplug: str = "", host_first: bool = True) -> Iterator[Rig]:
    with Broker(tmp) as broker, drives() as (bus, sims):
        weg_sim = sims[0]
        path = tmp / "b.toml"
        path.write_text(config(broker.url, bus.paths[0], tmp / "ob", sparkplug))  # type: ignore[attr-defined]
        node = EdgeNode(load_sparkplug_config(path))
        host = Host(broker)
        thread = LoopThread("node", node.start, node.stop)
        thread.start()
        try:
            rig = Rig(broker, bus, weg_sim, node, host, path)  # type: ignore[arg-type]
            rig.sims = sims
            yield rig
        finally:
            thread.stop()
            host.close()


def dbirthed(host: Host, *devices: str) -> bool:
    return all(host.of("DBIRTH", d) for d in devices)


def node_messages(host: Host) -> list[Message]:
    """What the edge node published (births, data, deaths), in arrival order."""
    return [
        m for m in host.snapshot() if m.kind in ("NBIRTH", "DBIRTH", "NDATA", "DDATA", "DDEATH")
    ]


def check_seq(msgs: list[Message]) -> None:
    """tck-id-payloads-sequence-num-incrementing, -nbirth-seq-num, -dbirth-seq,
    -ddata-seq, -ddeath-seq-num: one sequence 0..255 through the node's messages,
    NBIRTH 0, each next one more (mod 256)."""
    prev = None
    for m in msgs:
        seq = m.decoded().seq
        assert seq is not None and 0 <= seq <= 255, m.topic
        if m.kind == "NBIRTH":
            assert seq == 0
        elif prev is not None:
            assert seq == (prev + 1) % 256, (m.topic, prev, seq)
        prev = seq


def aliases(host: Host, device: str) -> dict[str, tuple[int, int]]:
    """name -> (alias, datatype) from the device's last DBIRTH."""
    birth = host.of("DBIRTH", device)[-1].decoded()
    return {m.name: (m.alias, m.datatype) for m in birth.metrics}  # type: ignore[misc]


def last_value(
    host: Host, device: str, alias: int, datatype: int, historical: bool = False
) -> object:
    for msg in reversed(host.of("DDATA", device)):
        for m in msg.decoded().metrics:
            if m.alias == alias and m.is_historical == historical:
                return m.value(datatype)
    return None


def test_births_seq_aliases_datatypes_and_data(tmp_path: Path) -> None:
    """tck-id-topic-structure, -topics-nbirth-topic, -nbirth-seq-num, -nbirth-bdseq-included,
    -nbirth-rebirth-metric, -payloads-nbirth-qos/retain, -dbirth-*, -ddata-*,
    -payloads-alias-*, -payloads-metric-datatype-*, -payloads-timestamp-in-UTC."""
    with rig(tmp_path) as r:
        host = r.host
        before = int(time.time() * 1000)
        host.wait(lambda: dbirthed(host, "weg", "cv"), "both DBIRTHs")
        r.weg.set(ACCEL, 123)
        r.weg.set(DECEL, 0xFFFE)  # -2 as an int16
        weg_alias = aliases(host, "weg")
        host.wait(
            lambda: last_value(host, "weg", weg_alias["accel"][0], DT["UInt16"]) == 123, "123"
        )
        host.wait(lambda: last_value(host, "weg", weg_alias["decel"][0], DT["Int16"]) == -2, "-2")
        after = int(time.time() * 1000)
        msgs = node_messages(host)
        (nbirth,) = host.of("NBIRTH")
        assert nbirth.topic == f"spBv1.0/{GROUP}/NBIRTH/{EDGE}"
        assert msgs[0] is not None and msgs[0].kind == "NBIRTH"
        assert {m.kind for m in msgs[1:3]} == {"DBIRTH"}  # the DBIRTHs first, then data
        for m in msgs:
            assert (m.qos, m.retain) == (0, False), m.topic
            parts = m.topic.split("/")
            assert parts[:2] == ["spBv1.0", GROUP] and parts[3] == EDGE
            assert len(parts) == (4 if m.kind.startswith("N") else 5), m.topic
            p = m.decoded()
            assert p.timestamp is not None and before - 1000 <= p.timestamp <= after + 1000
            for metric in p.metrics:
                assert metric.timestamp is not None
        check_seq(msgs)
        nb = {m.name: m for m in nbirth.decoded().metrics}
        assert nb["bdSeq"].datatype == DT["Int64"] and nb["bdSeq"].value(DT["Int64"]) == 0
        rebirth = nb["Node Control/Rebirth"]
        assert rebirth.datatype == DT["Boolean"] and rebirth.raw is False
        assert rebirth.value_field == "boolean_value" and rebirth.alias is None
        # every metric of a birth has a name, an alias and a datatype; aliases unique
        seen: set[int] = set()
        for birth in [nbirth, *host.of("DBIRTH")]:
            for metric in birth.decoded().metrics:
                assert metric.name and metric.datatype
                if metric.name == "Node Control/Rebirth":
                    continue
                assert metric.alias is not None and metric.alias not in seen
                seen.add(metric.alias)
        # datatypes from the point types; units and ranges as properties
        assert weg_alias["accel"][1] == DT["UInt16"] and weg_alias["decel"][1] == DT["Int16"]
        assert weg_alias["current"][1] == DT["Double"]  # scale 0.1
        wb = {m.name: m for m in host.of("DBIRTH", "weg")[-1].decoded().metrics}
        assert wb["ref"].properties["engUnit"] == (DT["String"], "rpm")
        assert wb["ref"].properties["engLow"] == (DT["Double"], 0.0)
        assert wb["ref"].properties["engHigh"] == (DT["Double"], 8192.0)
        assert wb["ref"].properties["readOnly"] == (DT["Boolean"], False)
        assert wb["accel"].properties["readOnly"] == (DT["Boolean"], True)
        # data: by alias only, no name and no datatype; historical only what was
        # read before the births (values waiting for the first connection)
        born_at = nbirth.decoded().timestamp
        assert born_at is not None
        for m in host.of("DDATA"):
            for metric in m.decoded().metrics:
                assert metric.name is None and metric.datatype is None and metric.alias in seen
                assert metric.timestamp is not None
                assert not metric.is_historical or metric.timestamp <= born_at


def test_dcmd_writes_through_the_checked_path_and_refusals(tmp_path: Path) -> None:
    """A DCMD write is read back in the next DDATA; a wrong type, a value out of
    range, an unknown metric and a read-only metric are refused (nothing written),
    logged and counted (tck-id-operational-behavior-data-commands-dcmd-*)."""
    with rig(tmp_path) as r:
        host = r.host
        host.wait(lambda: dbirthed(host, "weg"), "the DBIRTH")
        al = aliases(host, "weg")
        dcmd = f"spBv1.0/{GROUP}/DCMD/{EDGE}/weg"
        host.command(
            dcmd, encode_payload(encode_metric(name="ref", value_field="int_value", value=1000))
        )
        host.wait(lambda: last_value(host, "weg", al["ref"][0], DT["UInt16"]) == 1000, "read back")
        assert r.weg.get(weg.P_REFERENCE) == 1000
        # by alias (the drive takes decel times 0..): 50
        by_alias = encode_metric(alias=al["decel"][0], value_field="int_value", value=50)
        host.command(dcmd, encode_payload(by_alias))
        host.wait(lambda: last_value(host, "weg", al["decel"][0], DT["Int16"]) == 50, "50 back")
        assert r.weg.get(DECEL) == 50
        bad = [
            encode_metric(name="ref", value_field="float_value", value=5.0),  # wrong type
            encode_metric(name="ref", value_field="int_value", value=9000),  # above max 8192
            encode_metric(name="nope", value_field="int_value", value=1),  # unknown
            encode_metric(name="accel", value_field="int_value", value=7),  # read-only
            encode_metric(name="decel", value_field="int_value", value=40000),  # not an Int16
        ]
        for metric in bad:
            host.command(dcmd, encode_payload(metric))
        want = {"validation": 3, "unknown_metric": 1, "not_writable": 1}
        host.wait(lambda: r.node.dcmd_refused == want, f"refusals {want}")
        time.sleep(0.3)  # a poll or two: nothing was written
        assert r.weg.get(weg.P_REFERENCE) == 1000 and r.weg.get(ACCEL) != 7
        assert r.weg.get(DECEL) == 50


def test_rebirth_answers_with_nbirth_and_every_dbirth(tmp_path: Path) -> None:
    """tck-id-operational-behavior-data-commands-rebirth-action-1/2/3: NBIRTH with
    seq 0 and the same bdSeq, then every DBIRTH, before any data."""
    with rig(tmp_path) as r:
        host = r.host
        host.wait(lambda: dbirthed(host, "weg", "cv"), "births")
        n = len(node_messages(host))
        ncmd = f"spBv1.0/{GROUP}/NCMD/{EDGE}"
        host.command(ncmd, encode_payload(encode_metric(name="Node Control/Rebirth", value=True)))
        host.wait(lambda: len(host.of("NBIRTH")) == 2 and len(host.of("DBIRTH")) == 4, "rebirth")
        later = node_messages(host)[n:]
        # data already on its way when the command came may precede the NBIRTH; after
        # it, every DBIRTH before any data
        kinds = [m.kind for m in later]
        rebirth = kinds.index("NBIRTH")
        assert set(kinds[:rebirth]) <= {"DDATA"}, kinds
        assert kinds[rebirth : rebirth + 3] == ["NBIRTH", "DBIRTH", "DBIRTH"], kinds
        bd = [{m.name: m for m in b.decoded().metrics}["bdSeq"].raw for b in host.of("NBIRTH")]
        assert bd[0] == bd[1]
        check_seq(later)
        assert r.node.counts["rebirths"] == 1


def test_a_slave_unplugged_gets_a_ddeath_then_a_dbirth(tmp_path: Path) -> None:
    """tck-id-topics-ddeath-topic, -ddeath-seq-num, -payloads-ddeath-seq: DDEATH when
    the slave stops answering, DBIRTH when it answers again; the rest goes on."""
    with rig(tmp_path) as r:
        host = r.host
        host.wait(lambda: dbirthed(host, "weg", "cv"), "births")
        r.bus.unplug(2)  # type: ignore[attr-defined]
        r.sims[1].close()  # type: ignore[attr-defined]
        host.wait(lambda: host.of("DDEATH", "cv"), "the DDEATH of cv")
        assert host.of("DDEATH", "cv")[0].topic == f"spBv1.0/{GROUP}/DDEATH/{EDGE}/cv"
        assert not host.of("DDEATH", "weg")
        path = r.bus.replug(2)  # type: ignore[attr-defined]
        r.sims[1] = CV100Simulator()
        r.sims[1].serve(path, 5, baudrate=BAUD, parity="N")  # type: ignore[attr-defined]
        host.wait(lambda: len(host.of("DBIRTH", "cv")) == 2, "the DBIRTH of cv again")
        msgs = node_messages(host)
        kinds = [(m.kind, m.device) for m in msgs if m.device == "cv" and m.kind != "DDATA"]
        assert kinds == [("DBIRTH", "cv"), ("DDEATH", "cv"), ("DBIRTH", "cv")]
        death = next(i for i, m in enumerate(msgs) if m.kind == "DDEATH")
        rebirth = max(i for i, m in enumerate(msgs) if m.kind == "DBIRTH")
        assert not [m for m in msgs[death:rebirth] if m.kind == "DDATA" and m.device == "cv"]
        check_seq(msgs)
        # before its DDEATH, the device's values went stale: the Quality property 500
        quality = [
            metric.properties["Quality"]
            for m in msgs[:death]
            if m.kind == "DDATA" and m.device == "cv"
            for metric in m.decoded().metrics
            if "Quality" in metric.properties
        ]
        assert quality and set(quality) <= {(DT["Int32"], 500), (DT["Int32"], 0)}, quality


def test_primary_host_offline_store_and_forward_historical_and_rebirth(tmp_path: Path) -> None:
    """tck-id-message-flow-edge-node-birth-publish-phid-wait(-id/-online/-timestamp),
    -operational-behavior-edge-node-termination-host-offline(-timestamp),
    -operational-behavior-data-publish-*-historical: no birth before the host is
    online; its offline: an NDEATH and nothing more; an older STATE ignored; back
    online: births, then what was read meanwhile, in order, is_historical; a
    Rebirth in the middle of that backlog: births again, the backlog goes on."""
    with rig(tmp_path, 'primary_host_id = "scada"') as r:
        host = r.host
        time.sleep(0.5)
        assert not host.of("NBIRTH")  # waits for the host
        t_on = host.state(True)
        host.wait(lambda: dbirthed(host, "weg", "cv"), "births once online")
        al = aliases(host, "weg")["accel"][0]
        host.state(False, t_on - 1)  # older than the online: no disconnect
        time.sleep(0.5)
        assert not host.of("NDEATH") and r.node.stats()["born"]
        t_off = host.state(False, t_on + 1)
        host.wait(lambda: host.of("NDEATH"), "the NDEATH")
        # its own NDEATH, then the will: MQTT 5 "Disconnect with Will Message"
        host.wait(lambda: len(host.of("NDEATH")) == 2, "the will too")
        bd_birth = {m.name: m for m in host.of("NBIRTH")[0].decoded().metrics}["bdSeq"].raw
        for death in host.of("NDEATH"):
            assert {m.name: m for m in death.decoded().metrics}["bdSeq"].raw == bd_birth
            assert death.decoded().seq is None  # tck-id-topics-ndeath-seq
        n_off = len(node_messages(host))
        # a backlog longer than one batch of the node's pump (64 records): two
        # points change at each step
        dal = aliases(host, "weg")["decel"][0]
        values = list(range(1000, 1050))
        seen = r.node.reporter._s  # what the poller read (stored by exception)
        decels = [v - 900 for v in values]
        if decels[0] == r.weg.get(DECEL):  # the drive's own value already: no change
            decels = decels[1:]
        for v in values:
            r.weg.set(ACCEL, v)
            r.weg.set(DECEL, v - 900)
            deadline = time.monotonic() + 5
            while (seen["weg.accel"].value, seen["weg.decel"].value) != (v, v - 900):
                assert time.monotonic() < deadline, f"the poller never read {v}"
                time.sleep(0.01)
        host.state(True, t_off - 5)  # older than the offline: ignored
        time.sleep(0.5)
        assert len(host.of("NBIRTH")) == 1
        assert len(node_messages(host)) == n_off  # nothing while the host is offline
        # online, and at once a Rebirth: it comes while the backlog is being sent
        host.state(True, t_off + 1)
        ncmd = f"spBv1.0/{GROUP}/NCMD/{EDGE}"
        host.command(ncmd, encode_payload(encode_metric(name="Node Control/Rebirth", value=True)))

        def historical(alias: int) -> list[int]:
            """The stored values forwarded after the host came back."""
            out = []
            for msg in node_messages(host)[n_off:]:
                if msg.kind != "DDATA" or msg.device != "weg":
                    continue
                for m in msg.decoded().metrics:
                    if m.alias == alias and m.is_historical:
                        out.append(m.value(DT["Int16"] if alias == dal else DT["UInt16"]))
            return out

        host.wait(lambda: historical(al)[-1:] == [values[-1]], "the whole backlog")
        host.wait(lambda: len(host.of("NBIRTH")) == 3, "the rebirth")
        host.wait(lambda: len(host.of("DBIRTH")) == 6, "the rebirth's DBIRTHs")
        assert historical(al) == values  # in order, none lost, none twice
        assert historical(dal) == decels
        nb = [{m.name: m for m in b.decoded().metrics}["bdSeq"].raw for b in host.of("NBIRTH")]
        assert nb[1] == (nb[0] + 1) % 256 and nb[2] == nb[1]  # a new connect; a rebirth
        # no data between an NBIRTH and its DBIRTHs
        later = node_messages(host)[n_off:]
        for i, m in enumerate(later):
            if m.kind == "NBIRTH":
                assert [x.kind for x in later[i + 1 : i + 3]] == ["DBIRTH", "DBIRTH"]
        r.weg.set(ACCEL, 4242)
        host.wait(lambda: last_value(host, "weg", al, DT["UInt16"]) == 4242, "live again")
        check_seq(node_messages(host)[n_off:])


def _spawn(path: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "bridge", "--config", str(path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )


def test_bridge_sigkill_the_will_is_the_ndeath_with_the_births_bdseq(tmp_path: Path) -> None:
    """tck-id-payloads-ndeath-will-message(-qos/-retain), -message-flow-edge-node-birth-
    publish-will-message-*, -topics-nbirth-bdseq-matching, -payloads-nbirth-bdseq-repeat:
    the will (QoS 1, not retained) carries the NBIRTH's bdSeq; the next run's bdSeq
    is one more."""
    with Broker(tmp_path) as broker, drives() as (bus, _sim):
        path = tmp_path / "b.toml"
        path.write_text(config(broker.url, bus.paths[0], tmp_path / "ob"))  # type: ignore[attr-defined]
        host = Host(broker)
        try:
            for run in (1, 2):
                proc = _spawn(path)
                try:
                    host.wait(lambda n=run: len(host.of("NBIRTH")) == n, f"NBIRTH {run}")
                    os.kill(proc.pid, signal.SIGKILL)
                    proc.wait(10)
                    host.wait(lambda n=run: len(host.of("NDEATH")) == n, f"NDEATH {run}")
                finally:
                    if proc.poll() is None:
                        os.kill(proc.pid, signal.SIGKILL)
                        proc.wait(10)
            births = [
                {m.name: m for m in b.decoded().metrics}["bdSeq"].raw for b in host.of("NBIRTH")
            ]
            deaths = host.of("NDEATH")
            assert births == [0, 1]
            for death, bd in zip(deaths, births, strict=True):
                assert death.topic == f"spBv1.0/{GROUP}/NDEATH/{EDGE}"
                assert death.qos == 1 and not death.retain
                assert death.decoded().seq is None
                (metric,) = death.decoded().metrics
                assert (metric.name, metric.datatype, metric.raw) == ("bdSeq", DT["Int64"], bd)
        finally:
            host.close()


@pytest.mark.parametrize("how", ["sigterm", "sigint", "duration", "closed-pipe"])
def test_the_bridge_ends_on_a_signal_and_on_its_duration_with_its_ndeath(
    tmp_path: Path, how: str
) -> None:
    """``pyrtu bridge`` in Sparkplug mode ends with status 0 on SIGTERM, SIGINT,
    ``--duration`` and its output pipe closed by its reader (``| head``: it writes
    nothing before its end, so it watches the pipe), and says its NDEATH itself (the
    NBIRTH's bdSeq) before it goes."""
    with Broker(tmp_path) as broker, drives() as (bus, _sim):
        path = tmp_path / "b.toml"
        path.write_text(config(broker.url, bus.paths[0], tmp_path / "ob"))  # type: ignore[attr-defined]
        host = Host(broker)
        argv = [sys.executable, "-m", "pyrtu", "bridge", "--config", str(path)]
        if how == "duration":
            argv += ["--duration", "3"]
        proc = subprocess.Popen(
            argv,
            stdout=subprocess.PIPE if how == "closed-pipe" else subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
        )
        try:
            host.wait(lambda: len(host.of("NBIRTH")) == 1, "the NBIRTH")
            if how == "closed-pipe":
                assert proc.stdout is not None
                proc.stdout.close()  # the reader gone
            elif how != "duration":
                proc.send_signal(signal.SIGTERM if how == "sigterm" else signal.SIGINT)
            code = proc.wait(30)  # a safety net, not a measure
            assert proc.stderr is not None
            err = proc.stderr.read().decode()
            assert code == 0, err
            assert "Traceback" not in err
            # its own NDEATH, then (MQTT 5 DISCONNECT with reason 0x04, as
            # tck-id-payloads-ndeath-will-message-publisher-disconnect-mqtt50 requires)
            # the will the broker sends: the same message twice
            host.wait(lambda: len(host.of("NDEATH")) == 2, "its NDEATH and its will")
            (birth,) = host.of("NBIRTH")
            bd = {m.name: m for m in birth.decoded().metrics}["bdSeq"].raw
            for death in host.of("NDEATH"):
                (metric,) = death.decoded().metrics
                assert (metric.name, metric.raw) == ("bdSeq", bd)
        finally:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(10)
            host.close()


def test_broker_sigkill_and_restart_a_new_session_with_births(tmp_path: Path) -> None:
    """A broker SIGKILLed and restarted: the node connects again with a new bdSeq
    (one more per CONNECT sent, tck-id-topics-nbirth-bdseq-increment) and births
    again on the new session (tck-id-message-flow-edge-node-birth-publish-connect)."""
    with rig(tmp_path) as r:
        host = r.host
        host.wait(lambda: dbirthed(host, "weg", "cv"), "births")
        first = {m.name: m for m in host.of("NBIRTH")[0].decoded().metrics}["bdSeq"].raw
        r.broker.kill()
        time.sleep(0.5)
        r.broker.start()
        host.wait(lambda: host.subscriptions >= 2, "the host back")
        host.wait(lambda: r.node.stats()["born"], "the node back")

        def bdseqs() -> list[int]:
            return [
                {m.name: m for m in b.decoded().metrics}["bdSeq"].raw for b in host.of("NBIRTH")
            ]

        if len(bdseqs()) < 2:  # the host came back after the node's births: it asks
            ncmd = f"spBv1.0/{GROUP}/NCMD/{EDGE}"
            host.command(
                ncmd, encode_payload(encode_metric(name="Node Control/Rebirth", value=True))
            )
        host.wait(lambda: len(bdseqs()) >= 2, "an NBIRTH of the new session")
        assert bdseqs()[-1] == r.node.session.bdseq and bdseqs()[-1] > first
        host.wait(lambda: len(host.of("DBIRTH")) >= 4, "the DBIRTHs of the new session")
        check_seq(node_messages(host)[-3:])


def test_a_json_mode_backlog_in_the_outbox_is_passed_by_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """An outbox the JSON mode left behind (records of a topic and a payload, no
    point updates): the edge node passes them by at its first births, logs the
    first once, counts them all, and publishes none of them."""
    from pyrtu.outbox.outbox import Outbox

    with Outbox(tmp_path / "ob") as box:
        for i in range(3):
            box.append(b'pyrtu/e1/line/1/weg.speed\n{"value":%d' % i, 0.0)
        box.flush()
    with caplog.at_level("ERROR", logger="pyrtu.sparkplug"), rig(tmp_path) as r:
        r.host.wait(lambda: r.node.counts["foreign_records"] == 3, "the old records passed by")
        r.host.wait(lambda: r.node.stats()["outbox_depth"] == 0, "released")
    assert len([x for x in caplog.records if "no point update" in x.getMessage()]) == 1


def test_a_broker_whose_certificate_does_not_verify_halts_the_node_naming_it(
    tmp_path: Path,
) -> None:
    """An ``mqtts://`` broker whose certificate the node does not trust (the
    system's CAs only): the node halts with the JSON mode's message, naming the
    broker (`pyrtu.bridge.mqtt.fatal_error`), and publishes nothing in plain text."""
    from pyrtu.drivers.aio import run as aio_run

    with Broker(tmp_path, tls=True) as broker, drives() as (bus, _sims):
        path = tmp_path / "b.toml"
        path.write_text(config(broker.url, bus.paths[0], tmp_path / "ob"))
        node = EdgeNode(load_sparkplug_config(path))

        async def main() -> None:
            await node.start(poll=False)
            try:
                await asyncio.wait_for(node.halted.wait(), 30)
            finally:
                await node.stop()

        aio_run(main())
    assert isinstance(node.fatal, ConnectionRefusedError)
    assert f"broker {broker.url.split('://')[1]}: its certificate does not verify" in str(
        node.fatal
    )
    assert node.counts["nbirth"] == 0
