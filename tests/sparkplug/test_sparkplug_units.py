"""The edge node's sans-I/O parts: the schema read from sparkplug_b.proto checked
against the specification's field numbers with an independent decoder
(sparkplug_host.py), datatypes and their value fields at their bounds, seq and
bdSeq wrapping, the primary host's STATE timestamps, the [sparkplug] table's
errors (file:line: key)."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from sparkplug_host import DT, decode, encode_metric, encode_payload

pytest.importorskip("google.protobuf", reason="protobuf is not installed (pyrtu[sparkplug])")

from pyrtu.poller import ConfigError, Point
from pyrtu.sparkplug import metrics
from pyrtu.sparkplug.config import load_sparkplug_config
from pyrtu.sparkplug.payload import ProtoSyntaxError, datatype_numbers, parse_proto, payload_class
from pyrtu.sparkplug.session import BdSeqStore, HostState


def test_the_schema_s_datatypes_are_the_specification_s() -> None:
    numbers = datatype_numbers()
    assert {k: numbers[k] for k in DT} == DT
    assert numbers["DateTimeArray"] == 34 and numbers["Unknown"] == 0


def test_a_payload_built_with_the_schema_decodes_with_the_independent_decoder() -> None:
    p = payload_class()()
    p.timestamp = 1_700_000_000_123
    p.seq = 255
    m = p.metrics.add()
    m.name, m.alias, m.timestamp, m.datatype = "speed", 7, 1_700_000_000_000, DT["Float"]
    m.float_value = 1.5
    m.is_historical = True
    metrics.add_property(m.properties, "engUnit", DT["String"], "rpm")
    got = decode(p.SerializeToString())
    assert (got.timestamp, got.seq) == (1_700_000_000_123, 255)
    (gm,) = got.metrics
    assert (gm.name, gm.alias, gm.datatype, gm.raw, gm.is_historical) == ("speed", 7, 9, 1.5, True)
    assert gm.properties == {"engUnit": (DT["String"], "rpm")}


def test_a_command_encoded_by_hand_is_read_by_the_schema() -> None:
    body = encode_payload(encode_metric(name="ref", alias=9, value_field="int_value", value=5))
    p = payload_class().FromString(body)
    assert p.metrics[0].name == "ref" and p.metrics[0].alias == 9 and p.metrics[0].int_value == 5
    assert not p.HasField("seq")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("message M { optional string a = 1; ", "expected"),
        ("message M { optional Nope a = 1; }", "unknown type"),
        ("service S {}", "unexpected 'service'"),
        ("message M { map a = 1; }", "unexpected 'map'"),
    ],
)
def test_a_schema_outside_the_subset_is_refused(text: str, message: str) -> None:
    from pyrtu.sparkplug.payload import _qualify

    with pytest.raises(ProtoSyntaxError, match=message):
        _qualify(parse_proto(text))


def _point(**kw: object) -> Point:
    return Point("p", "bus", 1, "holding", 0, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kw", "want"),
    [
        ({}, "UInt16"),
        ({"type": "int16"}, "Int16"),
        ({"type": "int32"}, "Int32"),
        ({"type": "uint32"}, "UInt32"),
        ({"type": "int64"}, "Int64"),
        ({"type": "uint64"}, "UInt64"),
        ({"type": "float32"}, "Float"),
        ({"type": "float64"}, "Double"),
        ({"type": "string", "count": 2}, "String"),
        ({"type": "bool", "bit": 3}, "Boolean"),
        ({"scale": 0.1}, "Double"),
        ({"offset": -40}, "Double"),
        ({"enum": {0: "off", 1: "on"}}, "String"),
    ],
)
def test_the_datatype_follows_the_point_type(kw: dict[str, object], want: str) -> None:
    assert metrics.datatype(_point(**kw)) == DT[want]


def _metric(field: str, raw: object) -> object:
    m = payload_class().Metric()
    setattr(m, field, raw)
    return m


@pytest.mark.parametrize(
    ("dtype", "field", "raw", "want"),
    [
        ("UInt16", "int_value", 65535, 65535),
        ("UInt16", "int_value", 65536, None),
        ("Int16", "int_value", (1 << 32) - 32768, -32768),
        ("Int16", "int_value", (1 << 32) - 32769, None),
        ("Int16", "int_value", 32767, 32767),
        ("Int16", "int_value", 32768, None),
        ("Int8", "int_value", (1 << 32) - 128, -128),
        ("UInt8", "int_value", 256, None),
        ("Int32", "int_value", 1 << 31, -(1 << 31)),
        ("UInt32", "int_value", (1 << 32) - 1, (1 << 32) - 1),
        ("Int64", "long_value", 1 << 63, -(1 << 63)),
        ("UInt64", "long_value", (1 << 64) - 1, (1 << 64) - 1),
        ("UInt16", "float_value", 1.0, None),
        ("Boolean", "boolean_value", True, True),
        ("Boolean", "int_value", 1, None),
        ("String", "string_value", "x", "x"),
        ("Double", "double_value", float("inf"), None),
        ("Float", "float_value", 0.5, 0.5),
    ],
)
def test_a_command_value_is_checked_against_the_datatype(
    dtype: str, field: str, raw: object, want: object
) -> None:
    m = _metric(field, raw)
    if want is None:
        with pytest.raises(ValueError):
            metrics.get_value(m, DT[dtype])
    else:
        assert metrics.get_value(m, DT[dtype]) == want


@pytest.mark.parametrize(
    ("dtype", "value", "field", "raw"),
    [
        ("Int16", -2, "int_value", 0xFFFFFFFE),
        ("Int64", -1, "long_value", (1 << 64) - 1),
        ("UInt64", (1 << 64) - 1, "long_value", (1 << 64) - 1),
        ("Float", 0.1, "float_value", struct.unpack("<f", struct.pack("<f", 0.1))[0]),
        ("Boolean", True, "boolean_value", True),
    ],
)
def test_a_value_goes_to_its_datatype_s_field(
    dtype: str, value: object, field: str, raw: object
) -> None:
    m = payload_class().Metric()
    metrics.set_value(m, DT[dtype], value)  # type: ignore[arg-type]
    assert m.WhichOneof("value") == field and getattr(m, field) == raw
    null = payload_class().Metric()
    metrics.set_value(null, DT[dtype], None)
    assert null.is_null and null.WhichOneof("value") is None


def test_seq_wraps_from_255_to_0(tmp_path: Path) -> None:
    from pyrtu.sparkplug.session import EdgeSession

    cfg = load_sparkplug_config(_toml(tmp_path))
    s = EdgeSession(cfg)
    s.nbirth(1.0)  # seq 0
    got = [decode(s.ddeath(1.0)).seq for _ in range(256)]
    assert got[:2] == [1, 2] and got[254] == 255 and got[255] == 0
    assert decode(s.nbirth(2.0)).seq == 0


def test_bdseq_is_kept_on_disk_and_wraps(tmp_path: Path) -> None:
    store = BdSeqStore(tmp_path / "bd")
    assert [store.take() for _ in range(3)] == [0, 1, 2]
    assert BdSeqStore(tmp_path / "bd").take() == 3  # another run: the next one
    (tmp_path / "bd").write_text("255\n")
    assert store.take() == 255 and store.take() == 0
    (tmp_path / "bd").write_text("256\n")
    with pytest.raises(ValueError, match="not a bdSeq"):
        store.take()


def test_the_host_state_takes_equal_or_newer_timestamps_only() -> None:
    h = HostState()
    assert h.update(b'{"online": true, "timestamp": 100}') is True
    assert h.update(b'{"online": false, "timestamp": 99}') is None  # older: refused
    assert h.online is True
    assert h.update(b'{"online": false, "timestamp": 100}') is False  # equal: taken
    assert h.update(b'{"online": "yes", "timestamp": 200}') is None
    assert h.update(b'{"online": true}') is None
    assert h.update(b"\xff") is None
    assert h.online is False


def _toml(tmp: Path, sparkplug: str = 'group_id = "g"\n', devices: str = "") -> Path:
    path = tmp / "b.toml"
    path.write_text(
        f'[mqtt]\nurl = "mqtt://127.0.0.1:1"\nedge = "e1"\n\n[sparkplug]\n{sparkplug}\n'
        '[[bus]]\nname = "line"\nport = "/dev/null"\n\n'
        f"{devices}"
        '[[point]]\nname = "a"\nbus = "line"\nslave = 1\ntable = "holding"\naddress = 0\n'
        '[[point]]\nname = "b"\nbus = "line"\nslave = 2\ntable = "holding"\naddress = 0\n'
    )
    return path


def test_the_defaults_and_the_devices(tmp_path: Path) -> None:
    cfg = load_sparkplug_config(_toml(tmp_path))
    assert (cfg.group_id, cfg.edge_node_id, cfg.primary_host_id) == ("g", "e1", None)
    assert [d.id for d in cfg.devices] == ["line-1", "line-2"]
    assert [m.alias for d in cfg.devices for m in d.metrics] == [3, 4]  # after bdSeq 1, Rebirth 2
    assert cfg.bdseq_file.endswith(".bdseq")


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("", "b.toml:5: sparkplug: group_id: missing"),
        ('group_id = "a/b"\n', "b.toml:6: sparkplug: group_id 'a/b' holds '/'"),
        (
            'group_id = "g"\nedge_node_id = "e+"\n',
            "b.toml:7: sparkplug: edge_node_id 'e+' holds '+'",
        ),
        (
            'group_id = "g"\nprimary_host_id = "#"\n',
            "b.toml:7: sparkplug: primary_host_id '#' holds '#'",
        ),
        ('group_id = "g"\nspeed = 1\n', "b.toml:7: sparkplug: speed: unknown key"),
        ('group_id = ""\n', "b.toml:6: sparkplug: group_id must be a non-empty string"),
    ],
)
def test_a_bad_table_is_refused_naming_file_line_and_key(
    tmp_path: Path, table: str, message: str
) -> None:
    with pytest.raises(ConfigError) as e:
        load_sparkplug_config(_toml(tmp_path, table))
    assert str(e.value).startswith(message), str(e.value)


def test_two_devices_whose_ids_differ_only_in_case_are_refused(tmp_path: Path) -> None:
    devices = (
        '[[device]]\nbus = "line"\nslave = 1\nprofile = "cfw701"\nname = "Pump"\n'
        '[[device]]\nbus = "line"\nslave = 2\nprofile = "cfw701"\nname = "pump"\n'
    )
    with pytest.raises(ConfigError, match="device ids must differ, case aside"):
        load_sparkplug_config(_toml(tmp_path, devices=devices))


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", "bridge", *args], capture_output=True, text=True, env=env,
        timeout=60,
    )  # fmt: skip


def test_check_names_the_edge_node_and_its_devices(tmp_path: Path) -> None:
    out = _cli("--check", str(_toml(tmp_path)))
    assert out.returncode == 0, out.stderr
    assert "Sparkplug edge node g/e1, 2 devices, 2 metrics" in out.stdout


def test_a_config_error_exits_2_with_file_line_and_key(tmp_path: Path) -> None:
    out = _cli("--config", str(_toml(tmp_path, 'group_id = "g"\nedge_node_id = "a#"\n')))
    assert out.returncode == 2
    assert "b.toml:7: sparkplug: edge_node_id 'a#' holds '#'" in out.stderr
    assert "Traceback" not in out.stderr


def test_two_metrics_whose_names_differ_only_in_case_are_refused(tmp_path: Path) -> None:
    path = _toml(tmp_path)
    path.write_text(
        path.read_text()
        + '[[point]]\nname = "A"\nbus = "line"\nslave = 1\ntable = "holding"\naddress = 1\n'
    )
    with pytest.raises(ConfigError, match="metric names 'a' and 'A' differ only in case"):
        load_sparkplug_config(path)


def test_a_metric_never_read_is_born_null(tmp_path: Path) -> None:
    """tck-id-operational-behavior-data-publish-dbirth-values: is_null, no value."""
    from pyrtu.sparkplug.session import EdgeSession, LatestValue

    cfg = load_sparkplug_config(_toml(tmp_path))
    s = EdgeSession(cfg)
    dev = cfg.devices[0]
    never = decode(s.dbirth(dev, {}, 1.0)).metrics[0]
    assert never.is_null and never.value_field is None
    assert never.properties["Quality"] == (DT["Int32"], 500)
    read = decode(s.dbirth(dev, {"a": LatestValue(7, 2.0)}, 3.0)).metrics[0]
    assert not read.is_null and (read.value_field, read.raw) == ("int_value", 7)
    assert read.timestamp == 2000 and "Quality" not in read.properties


def test_a_dbirth_of_10000_metrics_is_built_and_decoded(tmp_path: Path) -> None:
    """The issue's target: a 10,000-metric DBIRTH, read back whole by the host's
    own decoder (names, aliases, datatypes in order)."""
    from dataclasses import replace

    from pyrtu.sparkplug.session import EdgeSession, LatestValue

    cfg = load_sparkplug_config(_toml(tmp_path))
    points = [Point(f"m{i}", "line", 9, "holding", i % 60000) for i in range(10_000)]
    (dev,) = metrics.devices(points, {}, first_alias=3)
    session = EdgeSession(replace(cfg, devices=(dev,)))
    body = session.dbirth(dev, {f"m{i}": LatestValue(i % 65536, 1.0) for i in range(10_000)}, 2.0)
    got = decode(body).metrics
    assert len(got) == 10_000
    assert [m.name for m in got] == [f"m{i}" for i in range(10_000)]
    assert [m.alias for m in got] == list(range(3, 10_003))
    assert {m.datatype for m in got} == {DT["UInt16"]} and got[-1].raw == 9_999
