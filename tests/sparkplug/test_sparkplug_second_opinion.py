"""A second opinion on what the edge node publishes: pysparkplug and mqtt-spb-wrapper
(PyPI), each in a virtual environment of its own under build/ (made once with pip,
kept between runs: they pin paho-mqtt 1.6.1, and mqtt-spb-wrapper protobuf 3.20),
decode the node's NBIRTH, DBIRTHs and DDATA as the tests' host application
(sparkplug_host.py) received them; their decoding must match the host's.

Their side is scripted in tests/sparkplug/second_opinion/.  pysparkplug resolves
a DDATA's aliases with the device's DBIRTH; mqtt-spb-wrapper drops a metric
without a datatype (it expects one in every DDATA, a pre-3.0 habit), so its DDATA
is compared on the wire fields it keeps (alias, raw value)."""

from __future__ import annotations

import json
import math
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import test_sparkplug_node as node_tests
from sparkplug_host import DT, Message, Metric

pytest.importorskip("google.protobuf", reason="protobuf is not installed (pyrtu[sparkplug])")
pytest.importorskip("pyrtu.vbus")

ROOT = Path(__file__).resolve().parents[2]
SIDE = Path(__file__).resolve().parent / "second_opinion"
PEERS = {
    "pysparkplug": ("pysparkplug==0.6.1", "decode_pysparkplug.py"),
    "spb_wrapper": ("mqtt-spb-wrapper==2.1.2", "decode_spb_wrapper.py"),
}


def peer_python(name: str) -> str:
    """The python of ``name``'s environment (build/sparkplug-<name>/, made when
    missing); skips when pip cannot install it here (no index reachable)."""
    spec = PEERS[name][0]
    home = ROOT / "build" / f"sparkplug-{name}"
    python, marker = home / "bin" / "python", home / ".installed"
    if python.exists() and marker.exists() and marker.read_text() == spec:
        return str(python)
    subprocess.run([sys.executable, "-m", "venv", "--clear", str(home)], check=True, timeout=300)
    done = subprocess.run(
        [str(python), "-m", "pip", "install", "--disable-pip-version-check", "-q", spec],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"pip could not install {spec} here: {done.stderr[-500:]}")
    marker.write_text(spec)
    return str(python)


def decode_with(name: str, msgs: list[Message]) -> list[Any]:
    items = [[m.kind, m.device, m.payload.hex()] for m in msgs]
    done = subprocess.run(
        [peer_python(name), str(SIDE / PEERS[name][1])],
        input=json.dumps(items), capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, f"{name} failed: {done.stderr}"
    return list(json.loads(done.stdout))


def same_value(mine: Any, theirs: Any, datatype: int) -> bool:
    if datatype == DT["Float"] and mine is not None and theirs is not None:
        return math.isclose(float(theirs), mine, rel_tol=1e-6)
    return bool(mine == theirs)


@pytest.fixture(scope="module")
def captured(tmp_path_factory: pytest.TempPathFactory) -> list[Message]:
    """The node's NBIRTH, DBIRTHs and DDATA (unsigned, signed and scaled values).

    A negative Int16 is left out: the node writes it in int_value as the 32-bit
    two's complement (-2: 4294967294, as Eclipse Tahu does), which pysparkplug 0.6.1
    refuses ("Int16 overflow"): it wants the 16-bit one (65534); the specification
    names the field (uint32) and not the encoding (docs/sparkplug.md)."""
    tmp = tmp_path_factory.mktemp("second")
    with node_tests.rig(tmp) as r:
        host = r.host
        host.wait(lambda: node_tests.dbirthed(host, "weg", "cv"), "both DBIRTHs")
        al = node_tests.aliases(host, "weg")
        r.weg.set(node_tests.ACCEL, 123)
        r.weg.set(node_tests.DECEL, 77)
        host.wait(
            lambda: node_tests.last_value(host, "weg", al["decel"][0], DT["Int16"]) == 77, "77"
        )
        host.wait(
            lambda: node_tests.last_value(host, "weg", al["accel"][0], DT["UInt16"]) == 123, "123"
        )
        msgs = [m for m in host.snapshot() if m.kind in ("NBIRTH", "DBIRTH", "DDATA")]
    assert [m.kind for m in msgs[:3]] == ["NBIRTH", "DBIRTH", "DBIRTH"]
    return msgs


def births_datatypes(msgs: list[Message]) -> dict[tuple[str | None, int], tuple[str, int]]:
    """(device, alias) -> (name, datatype) from the births, as the host reads them."""
    out: dict[tuple[str | None, int], tuple[str, int]] = {}
    for m in msgs:
        if m.kind.endswith("BIRTH"):
            for metric in m.decoded().metrics:
                if metric.alias is not None:
                    assert metric.name is not None and metric.datatype is not None
                    out[(m.device, metric.alias)] = (metric.name, metric.datatype)
    return out


def test_pysparkplug_decodes_births_and_data_as_the_host_does(captured: list[Message]) -> None:
    theirs = decode_with("pysparkplug", captured)
    names = births_datatypes(captured)
    assert len(theirs) == len(captured)
    for msg, their in zip(captured, theirs, strict=True):
        mine = msg.decoded()
        assert (their["seq"], their["timestamp"]) == (mine.seq, mine.timestamp), msg.topic
        assert len(their["metrics"]) == len(mine.metrics)
        for m, t in zip(mine.metrics, their["metrics"], strict=True):
            assert isinstance(m, Metric)
            if msg.kind == "DDATA":  # by alias: name and datatype from the DBIRTH
                assert m.alias is not None
                name, datatype = names[(msg.device, m.alias)]
            else:
                assert m.name is not None and m.datatype is not None
                name, datatype = m.name, m.datatype
            assert (t["name"], t["alias"], t["datatype"]) == (name, m.alias, datatype)
            assert (t["timestamp"], t["is_historical"], t["is_null"]) == (
                m.timestamp, m.is_historical, m.is_null)  # fmt: skip
            assert same_value(m.value(datatype), t["value"], datatype), (name, t["value"])


def _raw(metric: dict[str, Any]) -> Any:
    """The value field of a MessageToDict metric (64-bit integers as strings)."""
    key = next(k for k in metric if k.endswith("Value") and k != "value")
    v = metric[key]
    return int(v) if key in ("intValue", "longValue") else v


def test_mqtt_spb_wrapper_decodes_births_and_data_as_the_host_does(
    captured: list[Message],
) -> None:
    theirs = decode_with("spb_wrapper", captured)
    assert len(theirs) == len(captured)
    for msg, their in zip(captured, theirs, strict=True):
        mine = msg.decoded()
        assert their is not None, f"mqtt-spb-wrapper could not parse {msg.topic}"
        assert int(their["seq"]) == mine.seq and int(their["timestamp"]) == mine.timestamp
        metrics = their["metrics"]
        assert len(metrics) == len(mine.metrics)
        for m, t in zip(mine.metrics, metrics, strict=True):
            alias = t.get("alias")  # a string where it skipped the value (null)
            assert (None if alias is None else int(alias)) == m.alias
            assert int(t["timestamp"]) == m.timestamp
            assert bool(t.get("isHistorical", False)) == m.is_historical
            assert bool(t.get("isNull", False)) == m.is_null
            if msg.kind == "DDATA":
                assert "datatype" not in t and "name" not in t  # by alias only
                raw = _raw(t)
                if m.value_field == "float_value":
                    assert math.isclose(raw, m.raw, rel_tol=1e-6)
                else:
                    assert raw == m.raw, (m.alias, raw, m.raw)
                continue
            assert (t["name"], t["datatype"]) == (m.name, m.datatype)
            if m.is_null:
                assert "value" not in t
                continue
            assert m.datatype is not None
            value = m.value(m.datatype)
            if m.datatype == DT["Float"]:
                value = struct.unpack("<f", struct.pack("<f", value))[0]
            assert same_value(value, t["value"], m.datatype), (m.name, t["value"], value)
            for key, (ptype, pvalue) in m.properties.items():
                assert t["properties"]["key_value"][key] == pvalue, (m.name, key, ptype)
