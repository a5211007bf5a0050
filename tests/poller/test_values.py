"""A point's value in JSON and MQTT is the shortest decimal faithful to its register
(issue 27.12): a float32 holding 5.1 is ``5.1``, not ``5.099999904632568``; a uint16
214 scaled by 0.1 is ``21.4``, not ``21.400000000000002``.

Expected values come from the register's bits (`struct`), exact decimal arithmetic
(`decimal`) and the float32 constants as C and IEEE 754 give them, never from the
code under test; the outputs are read as the text a consumer receives: `pyrtu poll
--config --json`, `pyrtu read --json` and the bridge's MQTT payloads from a real
mosquitto."""

from __future__ import annotations

import json
import math
import re
import signal
import struct
from decimal import Decimal
from pathlib import Path

import pytest
from cli_helpers import pyrtu
from hypothesis import given
from hypothesis import strategies as st
from mqtt_broker import Broker, Client

from pyrtu.poller import Point
from pyrtu.poller.values import faithful_value, shortest_float32


def f32(bits: int) -> float:
    """The float32 of these bits, widened to a double (as decoding gives it)."""
    value: float = struct.unpack(">f", bits.to_bytes(4, "big"))[0]
    return value


def float32_of(x: float) -> float:
    value: float = struct.unpack(">f", struct.pack(">f", x))[0]
    return value


def point(**fields: object) -> Point:
    return Point("p", bus="b", slave=1, table="holding", address=0, **fields)  # type: ignore[arg-type]


# IEEE 754 binary32 at its edges; the decimals are C's FLT_MAX (3.40282347e+38), FLT_MIN
# (1.17549435e-38) and FLT_TRUE_MIN (1.40129846e-45) shortened to the fewest digits
# that still select the same float32 (as Java's Float.toString and numpy print them)
EDGES = [
    (0x7F7FFFFF, "3.4028235e+38"),  # the largest float32
    (0xFF7FFFFF, "-3.4028235e+38"),
    (0x00800000, "1.1754944e-38"),  # the smallest normal
    (0x007FFFFF, "1.1754942e-38"),  # the largest subnormal
    (0x00000001, "1e-45"),  # the smallest subnormal
    (0x80000001, "-1e-45"),
    (0x3F800001, "1.0000001"),  # the float32 after 1
    (0x4B7FFFFF, "16777215.0"),  # 2**24 - 1: every integer up to 2**24 is exact
    (0x00000000, "0.0"),
    (0x80000000, "-0.0"),
]


@pytest.mark.parametrize(("bits", "text"), EDGES, ids=[t for _, t in EDGES])
def test_float32_edges(bits: int, text: str) -> None:
    assert repr(shortest_float32(f32(bits))) == text
    assert json.dumps(faithful_value(point(type="float32"), f32(bits))) == text


@pytest.mark.parametrize("text", ["5.1", "0.1", "-273.15", "1e-07", "123456.7", "3.3333333"])
def test_float32_written_as_a_decimal_reads_back_as_it(text: str) -> None:
    """A float32 register set to a decimal of up to 8 digits: the decimal comes back."""
    assert repr(shortest_float32(float32_of(float(text)))) == text


def test_nan_and_infinities_stay_what_they_are() -> None:
    assert math.isnan(shortest_float32(f32(0x7FC00000)))
    assert shortest_float32(f32(0x7F800000)) == math.inf
    assert shortest_float32(f32(0xFF800000)) == -math.inf


def _digits(x: float) -> int:
    """Significant digits of repr(x)."""
    mantissa = re.sub(r"e.*", "", repr(abs(x))).replace(".", "").strip("0")
    return max(1, len(mantissa))


@given(st.integers(0, 0xFFFFFFFF))
def test_any_float32_is_faithful_and_shortest(bits: int) -> None:
    x = f32(bits)
    if not math.isfinite(x):
        return
    got = shortest_float32(x)
    assert struct.pack(">f", got) == struct.pack(">f", x)  # faithful: the same float32
    n = _digits(got)
    if n > 1 and x != 0:
        # no decimal of n - 1 digits selects it: neither of the two that bracket x
        d = Decimal(x)
        quantum = Decimal(1).scaleb(d.adjusted() - (n - 2))
        for rounding in ("ROUND_FLOOR", "ROUND_CEILING"):
            shorter = float(d.quantize(quantum, rounding=rounding))
            same = math.isfinite(shorter) and abs(shorter) <= f32(0x7F7FFFFF)
            assert not (same and struct.pack(">f", shorter) == struct.pack(">f", x)), (
                x,
                got,
                shorter,
            )


@pytest.mark.parametrize(
    ("kind", "scale", "offset", "raws"),
    [
        ("uint16", 0.1, 0.0, [214, 0, 1, 3, 65535, 12345]),
        ("int16", 0.01, 0.0, [-32768, -1, 7, 2999]),
        ("uint16", 0.1, -273.15, [0, 2731, 65535]),
        ("int32", 0.001, 0.0, [2**31 - 1, -(2**31), 1]),
        ("uint32", 1e-05, 0.0, [4294967295, 3]),
        ("uint16", 0.5, 0.25, [1, 3]),
        ("uint16", 10.0, 0.0, [5]),
    ],
)
def test_scaled_integers_at_their_resolution(
    kind: str, scale: float, offset: float, raws: list[int]
) -> None:
    p = point(type=kind, scale=scale, offset=offset)
    for raw in raws:
        exact = Decimal(raw) * Decimal(repr(scale)) + Decimal(repr(offset))
        got = faithful_value(p, raw * scale + offset)
        assert got == float(exact), (raw, got, exact)
        assert Decimal(json.dumps(got)) == exact


def test_float32_with_a_scale_and_unscaled_values_as_read() -> None:
    p = point(type="float32", scale=0.1, offset=-273.15)
    assert faithful_value(p, float32_of(5.1) * 0.1 - 273.15) == float(
        Decimal("5.1") * Decimal("0.1") - Decimal("273.15")
    )
    assert faithful_value(point(), 214) == 214 and faithful_value(point(), None) is None
    assert faithful_value(point(type="string", count=2), "ab") == "ab"


def test_a_value_no_register_of_the_point_holds_is_left_as_it_is() -> None:
    """Nothing is made up: 0.1 (a double, no float32 is it) and 0.123 (between two
    steps of 0.1) are returned unchanged, not snapped to a register's value."""
    assert faithful_value(point(type="float32"), 0.1) == 0.1
    assert faithful_value(point(scale=0.1), 0.123) == 0.123
    assert faithful_value(point(scale=0.1), math.inf) == math.inf


# ----------------------------------------------------------------------- the outputs

FLOATS = {0: 5.1, 3: f32(0x7F7FFFFF), 5: f32(0x00000001), 7: math.nan, 9: -273.15}


def registers() -> list[int]:
    """Holding registers 0..10: float32s (ABCD) at 0, 3, 5, 7, 9; uint16 214 at 2."""
    regs = [0] * 11
    for at, x in FLOATS.items():
        hi, lo = struct.unpack(">HH", struct.pack(">f", x))
        regs[at : at + 2] = [hi, lo]
    regs[2] = 214
    return regs


POINTS = """
[[bus]]
name = "t"
port = "{url}"
timeout = 1.0

[[point]]
name = "f"
bus = "t"
slave = 1
table = "holding"
address = 0
type = "float32"
interval = 0.05

[[point]]
name = "scaled"
bus = "t"
slave = 1
table = "holding"
address = 2
scale = 0.1
interval = 0.05

[[point]]
name = "big"
bus = "t"
slave = 1
table = "holding"
address = 3
type = "float32"
interval = 0.05

[[point]]
name = "tiny"
bus = "t"
slave = 1
table = "holding"
address = 5
type = "float32"
interval = 0.05

[[point]]
name = "nan"
bus = "t"
slave = 1
table = "holding"
address = 7
type = "float32"
interval = 0.05

[[point]]
name = "kelvin"
bus = "t"
slave = 1
table = "holding"
address = 9
type = "float32"
interval = 0.05
"""

#: each point's value as JSON text (nan: what each output writes instead)
WANT = {
    "f": "5.1",
    "scaled": "21.4",
    "big": "3.4028235e+38",
    "tiny": "1e-45",
    "kelvin": "-273.15",
}


@pytest.fixture
def slave_url() -> object:
    from pyrtu.cli._simulate_tcp import TcpThread
    from pyrtu.core.line import LineConfig
    from pyrtu.drivers.slave_base import SlaveBase
    from pyrtu.protocol.datastore import DataStore

    store = DataStore()
    store.holding_registers.add_range(0, registers())
    server = TcpThread(SlaveBase(1, store, line=LineConfig()), "127.0.0.1", 0)
    host, port = server.address
    try:
        yield f"tcp://{host}:{port}"
    finally:
        server.stop()


def value_texts(lines: list[str], key: str = "point") -> dict[str, str]:
    """The "value" of each JSON line as its text (what a consumer parses)."""
    out = {}
    for line in lines:
        m = re.search(r'"value": ?([^,}]*)', line)
        doc = json.loads(line)
        if m and key in doc:
            out[str(doc[key])] = m.group(1)
    return out


def test_poll_config_json(tmp_path: Path, slave_url: str) -> None:
    cfg = tmp_path / "points.toml"
    cfg.write_text(POINTS.format(url=slave_url))
    r = pyrtu("poll", "--config", cfg, "--duration", "1", "--json")
    assert r.code == 0, r.err
    got = value_texts(r.out.splitlines())
    assert got == {**WANT, "nan": '"nan"'}


def test_read_and_poll_json(slave_url: str) -> None:
    r = pyrtu("read", slave_url, "--slave", "1", "--type", "float32", "0", "--json")
    assert r.code == 0, r.err
    assert re.search(r'"values": \[5\.1\]', r.out), r.out
    args = ["--slave", "1", "--type", "float32", "0", "--duration", "0.5", "--json"]
    r = pyrtu("poll", slave_url, *args)
    assert r.code == 0, r.err
    reports = r.out.splitlines()
    assert reports and all(re.search(r'"values": \[5\.1\]', x) for x in reports), r.out


def test_bridge_payloads_and_set_results(tmp_path: Path, slave_url: str) -> None:
    """The values as published, and a set's result (the value read back): the set
    writes what the register already holds, so the read-back is the same value."""
    from cli_helpers import Background

    cfg = tmp_path / "bridge.toml"
    text = POINTS.format(url=slave_url).replace(
        'address = 0\ntype = "float32"\n', 'address = 0\ntype = "float32"\nwritable = true\n'
    )
    text = text.replace("scale = 0.1\n", "scale = 0.1\nwritable = true\n")
    base = "pyrtu/v/t/1"
    with Broker(tmp_path) as broker, Client(broker, [f"{base}/#"]) as sub:
        cfg.write_text(f'[mqtt]\nurl = "{broker.url}"\nedge = "v"\n' + text)
        bridge = Background("bridge", "--config", cfg, "--json")
        try:
            names = set(WANT) | {"nan"}
            sub.wait(lambda: names <= {t.rsplit("/", 1)[1] for t, *_ in sub.messages}, "values")
            sub.publish(f"{base}/f/set", b"5.1")
            sub.publish(f"{base}/scaled/set", b"21.4")
            sub.wait(lambda: sub.on(f"{base}/f/set/result") and sub.on(f"{base}/scaled/set/result"),
                     "the set results")  # fmt: skip
            bridge.proc.send_signal(signal.SIGTERM)
            assert bridge.finish().code == 0
        finally:
            bridge.kill()
        got = {}
        for topic, body, *_ in sub.messages:
            name = topic.rsplit("/", 1)[1]
            if name in names:
                m = re.search(rb'"value":([^,}]*)', body)
                assert m, body
                got[name] = m.group(1).decode()
        results = {
            p: re.search(rb'"value": ?([^,}]*)', sub.on(f"{base}/{p}/set/result")[0])
            for p in ("f", "scaled")
        }
    assert got == {**WANT, "nan": "null"}
    assert {p: m.group(1).decode() if m else None for p, m in results.items()} == {
        "f": "5.1",
        "scaled": "21.4",
    }
