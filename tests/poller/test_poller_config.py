"""The TOML loader: good files, and bad ones whose errors name the file, the line,
the table and key, and what is wrong."""

from __future__ import annotations

from pathlib import Path

import pytest

from pyrtu.poller import Bus, ConfigError, Device, Limits, Point, load_config, make_config
from pyrtu.poller.config import parse_config

MINIMAL = """\
[[bus]]
name = "line1"
port = "/dev/ttyUSB0"      # any port Master accepts
baudrate = 19200
parity = "E"

[[point]]
name = "cfw701.status"
bus = "line1"
slave = 1
table = "holding"
address = 680
type = "uint16"
interval = 0.1
"""

FULL = """\
[defaults]
bus = "line1"
interval = 0.5

[[bus]]
name = "line1"
port = "/dev/ttyUSB0"
baudrate = 38400
parity = "N"
stopbits = 2
timeout = 0.2
retries = 1
t35 = 0.002
timing = "weg"
mode = "rtu"
echo = false
share = 0.02
offline_after = 2
max_gap = 4

[[device]]
bus = "line1"
slave = 3
profile = "cfw701"
name = "pump"
interval = 0.2

[[device]]
bus = "line1"
slave = 7
profile = "acu"

[[device]]
bus = "line1"
slave = 1
max_registers = 16

[[point]]
name = "temp"
slave = 1
table = "input"
address = 10
type = "float32"
order = "CDAB"
scale = 0.1
deadband = 0.5

[[point]]
name = "serial"
slave = 1
table = "holding"
address = 100
type = "string"
count = 4
interval = 60

[[point]]
name = "run"
slave = 1
table = "coils"
address = 0
"""


def test_minimal_form(tmp_path: Path) -> None:
    f = tmp_path / "points.toml"
    f.write_text(MINIMAL)
    cfg = load_config(f)
    (bus,) = cfg.buses
    assert bus.name == "line1" and bus.port == "/dev/ttyUSB0"
    assert dict(bus.master) == {"baudrate": 19200, "parity": "E"}
    (p,) = cfg.points
    assert p == Point("cfw701.status", "line1", 1, "holding", 680, "uint16", interval=0.1)
    w = bus.wire()
    assert w.char == pytest.approx(11 / 19200, abs=1e-6) and w.t35 == pytest.approx(0.002005)


def test_full_form_devices_profiles_defaults() -> None:
    cfg = parse_config(FULL, "full.toml")
    bus = cfg.buses[0]
    assert bus.share == 0.02 and bus.offline_after == 2 and bus.limits == Limits(max_gap=4)
    assert bus.master["timing"] == "weg" and bus.master["stopbits"] == 2
    names = [p.name for p in cfg.points]
    assert names[:5] == ["pump.status", "pump.speed", "pump.current", "pump.fault", "pump.alarm"]
    assert "acu7.status" in names and "acu7.fault" in names
    pump = {p.name: p for p in cfg.points}
    assert pump["pump.current"].scale == 0.1 and pump["pump.status"].interval == 0.2
    assert pump["temp"].interval == 0.5 and pump["serial"].interval == 60  # [defaults]
    assert pump["run"].type == "bool"
    limits = cfg.limits("line1")
    assert limits[3].max_adu == 64 and limits[3].registers() == 29  # WEG telegrams
    assert limits[7].max_registers == 1  # Bonfiglioli: one register per FC 03
    assert limits[1] == Limits(max_registers=16, max_gap=4)  # device over bus


def bad(text: str) -> str:
    with pytest.raises(ConfigError) as e:
        parse_config(text, "points.toml")
    assert isinstance(e.value, ValueError)
    return str(e.value)


def test_semantic_errors_name_file_line_table_key() -> None:
    text = MINIMAL + '\n[[point]]\nname = "cfw701.speed"\nbus = "line1"\nslave = 1\n' \
        'table = "holding"\naddress = -1\n'  # fmt: skip
    msg = bad(text)
    assert msg == 'points.toml:21: point[1] ("cfw701.speed"): address: must be 0..65535, not -1'
    assert bad(MINIMAL.replace('parity = "E"', 'parity = "X"')) == (
        "points.toml:5: bus[0] (\"line1\"): parity: must be one of N, E, O, M, S, not 'X'"
    )
    msg = bad(MINIMAL.replace("address = 680", "adress = 680"))
    assert msg.startswith('points.toml:12: point[0] ("cfw701.status"): adress: unknown key')
    msg = bad(MINIMAL.replace('table = "holding"', 'table = "registers"'))
    assert msg.startswith('points.toml:11: point[0] ("cfw701.status"): table: must be one of')
    msg = bad(MINIMAL.replace('bus = "line1"', 'bus = "line2"'))
    assert msg == (
        "points.toml:9: point[0] (\"cfw701.status\"): bus: no bus named 'line2' (buses: line1)"
    )
    msg = bad(MINIMAL.replace("address = 680\n", ""))
    assert msg == 'points.toml:7: point[0] ("cfw701.status"): address: missing'
    assert "baudrate: must be an integer 50..4000000, not -5" in bad(MINIMAL.replace("19200", "-5"))
    msg = bad(MINIMAL.replace('parity = "E"', 'parity = "E"\ntimeout = 0'))
    assert msg == 'points.toml:6: bus[0] ("line1"): timeout: must be a positive number of ' \
        "seconds, not 0"  # fmt: skip


def test_more_bad_files() -> None:
    assert bad("") == "points.toml: no [[bus]] table"
    assert bad(MINIMAL.split("[[point]]")[0]) == "points.toml: no points to poll"
    assert "cfw701.status' is declared twice" in bad(MINIMAL + MINIMAL.split("\n\n")[1])
    assert "bus 'line1' is declared twice" in bad(MINIMAL.split("\n\n")[0] + "\n\n" + MINIMAL)
    assert bad("colour = 1\n" + MINIMAL).startswith("points.toml: unknown top-level key 'colour'")
    msg = bad(MINIMAL + '[[device]]\nbus = "line1"\nslave = 2\nprofile = "abb"\n')
    assert msg.startswith("points.toml:18: device[0]: profile: must be one of act, acu, cfw100")
    msg = bad(MINIMAL + '[[device]]\nbus = "line1"\nslave = 1\nmax_registers = 0\n')
    assert msg == "points.toml:18: device[0]: max_registers: must be an integer 1..125, not 0"
    msg = bad(MINIMAL.replace('type = "uint16"', 'type = "uint32"')
              + '[[device]]\nbus = "line1"\nslave = 1\nmax_registers = 1\n')  # fmt: skip
    assert "takes 2 registers, more than slave 1 reads per request (1)" in msg
    assert msg.startswith("points.toml:7: point[0]")
    msg = bad("[defaults]\ninterval = -1\n" + MINIMAL.replace("interval = 0.1\n", ""))
    assert msg.startswith('points.toml:1: point[0] ("cfw701.status"): interval: must be greater')
    assert "(from [defaults])" in msg


def test_syntax_errors_give_line_and_column(tmp_path: Path) -> None:
    msg = bad(MINIMAL.replace("slave = 1", "slave = = 1"))
    assert msg.startswith("points.toml: ") and "line 10" in msg and "column" in msg
    f = tmp_path / "bin.toml"
    f.write_bytes(b"\xff\xfe")
    with pytest.raises(ConfigError, match=r"bin.toml: not UTF-8"):
        load_config(f)
    with pytest.raises(ConfigError, match=r"nope.toml: no such file"):
        load_config(tmp_path / "nope.toml")


def test_python_declaration() -> None:
    bus = Bus("line1", "loop://", {"baudrate": 115200, "parity": "N"})
    cfg = make_config(
        [bus],
        [Point("a", "line1", 1, "holding", 0), Point("b", "line1", 1, "holding", 1)],
        [Device("line1", 1, Limits(max_registers=8))],
    )
    assert cfg.limits("line1")[1].max_registers == 8
    with pytest.raises(ValueError, match="parity"):
        Bus("x", "loop://", {"parity": "Q"})
    with pytest.raises(ValueError, match="unknown key"):
        Bus("x", "loop://", {"baud": 9600})
    with pytest.raises(ValueError, match="share"):
        Bus("x", "loop://", share=1.5)
    with pytest.raises(ConfigError, match="no bus named"):
        make_config([bus], [Point("a", "line2", 1, "holding", 0)])
