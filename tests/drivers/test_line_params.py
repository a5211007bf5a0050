"""One validator for line parameters: the same bad value gets the same words from
the API (ValueError/TypeError naming the keyword), the TOML loader (file:line and
key) and the command line (exit 2 naming the flag); one port on two buses or two
``--port`` is a usage error naming the duplicate."""

from __future__ import annotations

import asyncio
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from cli_helpers import pyrtu as run_cli

import pyrtu
from pyrtu import LineConfig, Master
from pyrtu.drivers._portname import first_duplicate, port_key, same_port
from pyrtu.drivers.aio import AsyncMaster, AsyncSlave
from pyrtu.poller import ConfigError, load_config
from pyrtu.vbus import VirtualBus

#: (keyword, TOML text, CLI text, Python value, the words every path says)
BAD = [
    ("baudrate", "9223372036854775807", "9223372036854775807", 2**63 - 1,
     "must be an integer 50..4000000, not 9223372036854775807"),
    ("baudrate", "20000000", "20000000", 20_000_000,
     "must be an integer 50..4000000, not 20000000"),
    ("baudrate", "1000000000", "1000000000", 10**9,
     "must be an integer 50..4000000, not 1000000000"),
    ("baudrate", "0", "0", 0, "must be an integer 50..4000000, not 0"),
    ("baudrate", "49", "49", 49, "must be an integer 50..4000000, not 49"),
    ("parity", '"X"', "X", "X", "must be one of N, E, O, M, S, not 'X'"),
    ("bytesize", "9", "9", 9, "must be 7 or 8, not 9"),
    ("stopbits", "3", "3", 3, "must be 1, 1.5 or 2, not 3"),
    ("timing", '"fast"', "fast", "fast", "must be 'modbus' or 'weg', not 'fast'"),
    ("mode", '"tcp"', "tcp", "tcp", "must be 'rtu' or 'ascii', not 'tcp'"),
]  # fmt: skip
IDS = [f"{b[0]}={b[2]}" for b in BAD]

TOML = """\
[[bus]]
name = "line1"
port = "{port}"
{key} = {value}

[[point]]
name = "speed"
bus = "line1"
slave = 1
table = "holding"
address = 0
"""


@pytest.mark.parametrize(("key", "toml", "cli", "value", "words"), BAD, ids=IDS)
def test_the_api_says_it_naming_the_keyword(
    key: str, toml: str, cli: str, value: Any, words: str, backend: ModuleType, tmp_path: Path
) -> None:
    """LineConfig, the framer, Master, AsyncMaster, Slave, AsyncSlave and the virtual
    bus: the same error, raised before any port is opened (the path does not exist)."""
    nowhere = str(tmp_path / "no-such-port")
    expected = f"{key} {words}"

    def master() -> None:
        Master(nowhere, **{key: value})

    def aio_master() -> None:
        AsyncMaster(nowhere, **{key: value})

    def slave() -> None:
        pyrtu.Slave(nowhere, 1, **{key: value})

    def aio_slave() -> None:
        async def make() -> None:
            AsyncSlave(nowhere, 1, **{key: value})

        asyncio.run(make())

    makers = [lambda: LineConfig(**{key: value}), master, aio_master, slave, aio_slave]
    if key != "mode":  # the RTU framer has no mode
        makers.append(lambda: backend.Framer("master", **{key: value}))
    if key not in ("mode", "timing"):  # the bus is a wire: a byte format, no framing
        makers.append(lambda: VirtualBus(2, **{key: value}))
    for make in makers:
        with pytest.raises(ValueError) as info:  # TypeError too for a wrong type
            make()
        assert str(info.value) == expected


def test_a_wrong_type_is_a_type_error() -> None:
    for kwargs in ({"baudrate": 9600.0}, {"baudrate": True}, {"parity": 1}, {"bytesize": "8"}):
        with pytest.raises(TypeError, match=next(iter(kwargs))):
            LineConfig(**kwargs)
        with pytest.raises(TypeError, match=next(iter(kwargs))):
            Master("/nonexistent/port", **kwargs)


def test_the_supported_range_is_accepted_everywhere() -> None:
    low, high = LineConfig(baudrate=50, parity="N"), LineConfig(baudrate=4_000_000)
    assert low.times.char_us == 200_000  # 10 bits at 50 baud
    assert high.times.char_us == 3  # 11 bits: 2.75 us, still a positive character time
    assert pyrtu.Framer("master", baudrate=4_000_000).options.baudrate == 4_000_000


@pytest.mark.parametrize(("key", "toml", "cli", "value", "words"), BAD, ids=IDS)
def test_the_toml_loader_says_it_with_file_and_line(
    key: str, toml: str, cli: str, value: Any, words: str, tmp_path: Path
) -> None:
    path = tmp_path / "points.toml"
    path.write_text(TOML.format(port=tmp_path / "p", key=key, value=toml))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value) == f'points.toml:4: bus[0] ("line1"): {key}: {words}'


@pytest.mark.parametrize(("key", "toml", "cli", "value", "words"), BAD, ids=IDS)
def test_the_command_line_says_it_naming_the_flag(
    key: str, toml: str, cli: str, value: Any, words: str, tmp_path: Path
) -> None:
    r = run_cli("read", tmp_path / "no-such-port", "0", f"--{key}", cli)
    assert r.code == 2
    last = r.err.strip().splitlines()[-1]
    assert last.startswith("pyrtu read: error: argument ") and f"--{key}: {words}" in last, r.err
    assert "Traceback" not in r.err


def test_the_poller_command_says_it_with_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "points.toml"
    path.write_text(TOML.format(port=tmp_path / "p", key="baudrate", value="9223372036854775807"))
    r = run_cli("poll", "--config", path, "--duration", "1")
    assert r.code == 2 and "Traceback" not in r.err
    assert (
        'points.toml:4: bus[0] ("line1"): baudrate: '
        "must be an integer 50..4000000, not 9223372036854775807" in r.err
    )


# -- one port twice ----------------------------------------------------------------------------


def test_port_names_compare_by_what_they_resolve_to(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "P").touch()
    (tmp_path / "link").symlink_to(tmp_path / "P")
    assert same_port("P", "./P") and same_port(str(tmp_path / "P"), "sub/../P")
    assert same_port("link", "P")
    assert not same_port("P", "Q")
    assert not same_port("loop://", "loop://")  # two URLs are two connections
    assert port_key("socket://host:502") is None
    assert first_duplicate(["A", "loop://", "loop://", "B", "./A"]) == (0, 4)
    assert first_duplicate(["A", "B"]) is None


def test_two_buses_on_one_port_name_the_second(tmp_path: Path) -> None:
    path = tmp_path / "two.toml"
    path.write_text(
        f'[[bus]]\nname = "a"\nport = "{tmp_path}/P"\n\n'
        f'[[bus]]\nname = "b"\nport = "{tmp_path}/x/../P"\n\n'
        '[[point]]\nname = "s"\nbus = "a"\nslave = 1\ntable = "holding"\naddress = 0\n'
    )
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text = str(info.value)
    assert text.startswith('two.toml:7: bus[1] ("b"): port: ') and 'bus[0] ("a")' in text
    r = run_cli("poll", "--config", path, "--duration", "1")
    assert r.code == 2 and "two.toml:7" in r.err and "busy" not in r.err


def test_simulate_refuses_one_port_given_twice(tmp_path: Path) -> None:
    with VirtualBus(2, baudrate=19200, parity="N", directory=str(tmp_path)) as bus:
        drop = bus.paths[1]
        dotted = str(Path(drop).parent / "." / Path(drop).name)
        for again in (drop, dotted, bus.tty_paths[1]):
            r = run_cli("simulate", "cfw701", "-p", drop, "-p", again, "-P", "N")
            assert r.code == 2, r.err
            assert "--port" in r.err and "busy" not in r.err and "Traceback" not in r.err
            assert drop in r.err
