"""LineConfig: one validated line description for the framer, protocols and drivers."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest

from pyrtu import BONFIGLIOLI
from pyrtu.core.ascii import AsciiFramer, make_framer
from pyrtu.core.line import LineConfig
from pyrtu.core.timing import Timing


def test_defaults_and_derived_timing() -> None:
    line = LineConfig()
    assert (line.baudrate, line.parity, line.stopbits, line.bytesize) == (19200, "E", 1, 8)
    assert line.mode == "rtu" and line.timing == "modbus" and line.bits == 11
    assert line.times == Timing(573, 859, 2005)
    assert line.char_time == pytest.approx(573e-6)
    assert line.t35_time == pytest.approx(2005e-6) == line.frame_gap
    assert line.wire_time(10) == pytest.approx(5730e-6)


def test_rules_overrides_and_modes() -> None:
    fast = LineConfig(baudrate=115200, parity="n")
    assert fast.parity == "N" and fast.bits == 10
    assert fast.times == Timing(87, 750, 1750)
    assert LineConfig(baudrate=115200, timing="weg").times == Timing(95, 860, 2005)
    assert LineConfig(t35=0.0, t15=0.0).times.t35_us == 0
    ascii_line = LineConfig(mode="ascii")
    assert ascii_line.frame_gap == 0.0
    assert isinstance(make_framer(ascii_line, "master"), AsciiFramer)
    line = LineConfig(rules=BONFIGLIOLI)
    assert dict(line.rules) == dict(BONFIGLIOLI)
    with pytest.raises(TypeError):
        line.rules[5] = (None, None)  # type: ignore[index]
    assert line.replace(baudrate=9600).baudrate == 9600
    assert LineConfig.of(line, strict=True).strict and LineConfig.of(None).baudrate == 19200
    assert LineConfig() == LineConfig() and hash(LineConfig()) == hash(LineConfig())


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"baudrate": 0}, "baudrate"),
        ({"baudrate": 9600.0}, "baudrate"),
        ({"parity": "X"}, "parity"),
        ({"parity": 1}, "parity"),
        ({"stopbits": 3}, "stopbits"),
        ({"bytesize": 6}, "bytesize"),
        ({"mode": "tcp"}, "mode"),
        ({"timing": "fast"}, "timing"),
        ({"t15": -1}, "t15"),
        ({"t35": float("inf")}, "t35"),
        ({"t35": float("nan")}, "t35"),
        ({"max_adu": 3}, "max_adu"),
        ({"strict": "yes"}, "strict"),
        ({"rules": {0: (None, None)}}, "function code"),
        ({"flush_timeout": -0.1}, "flush_timeout"),
        ({"inter_char": 0}, "inter_char"),
    ],
)
def test_bad_values_name_the_keyword(kwargs: dict[str, object], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        LineConfig(**kwargs)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=name):
        LineConfig().replace(**kwargs)


def test_framer_and_parse_stream_take_a_line(backend: ModuleType) -> None:
    line = LineConfig(baudrate=9600, rules=BONFIGLIOLI)
    adu = backend.add_crc(bytes.fromhex("01640001"))
    f = backend.Framer("slave", line=line)
    f.receive_data(adu, 1.0)
    ev = f.next_event()
    assert ev is not None and ev.adu == adu
    assert [fr.adu for fr in backend.parse_stream(adu, "slave", line=line)] == [adu]
    assert make_framer(line, "slave", backend).options == f.options
    with pytest.raises(TypeError, match="not both"):
        backend.Framer("slave", line=line, baudrate=9600)
    with pytest.raises(TypeError, match="not both"):
        backend.parse_stream(adu, line=line, strict=True)
    with pytest.raises(TypeError, match="LineConfig"):
        backend.Framer("slave", line={"baudrate": 9600})
    with pytest.raises(ValueError, match="ASCII"):  # make_framer() picks AsciiFramer
        backend.Framer("slave", line=LineConfig(mode="ascii"))


def test_virtual_bus_takes_a_line() -> None:
    from pyrtu.vbus import VirtualBus

    line = LineConfig(baudrate=9600, parity="N", stopbits=2)
    bus = VirtualBus(2, line=line)  # not started: only the configuration
    assert bus.baudrate == 9600 and bus.bits == line.bits == 11
    assert bus.char_time == pytest.approx(line.char_time, abs=1e-6)
    with pytest.raises(TypeError, match="LineConfig"):
        VirtualBus(2, line={"baudrate": 9600})  # type: ignore[arg-type]


def test_line_and_keywords_refused_the_same_way_everywhere(
    backend: ModuleType, tmp_path: Path
) -> None:
    """One rule (`pyrtu.core.line.line_from`) for ``line=`` with line keywords: every
    constructor refuses both, naming the keyword given (the virtual bus ignored
    the keywords, the framers and slaves said only "baudrate=...")."""
    from pyrtu.drivers.aio import AsyncMaster
    from pyrtu.drivers.master import Master
    from pyrtu.drivers.slave import Slave
    from pyrtu.vbus import VirtualBus

    line = LineConfig(baudrate=9600)
    missing = str(tmp_path / "no-such-port")
    makers = [
        lambda: backend.Framer("slave", line=line, parity="N"),
        lambda: backend.parse_stream(b"", line=line, parity="N"),
        lambda: VirtualBus(2, line=line, parity="N"),
        lambda: Master(missing, line=line, parity="N"),
        lambda: AsyncMaster(missing, line=line, parity="N"),
        lambda: Slave(missing, line=line, parity="N"),
    ]
    for make in makers:
        with pytest.raises(TypeError, match=r"give line= or the line keywords \(parity\)"):
            make()
