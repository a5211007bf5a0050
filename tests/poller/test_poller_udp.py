"""``udp://`` buses in the poller's configuration (#31.5): ``pyrtu poll --config`` polls
a device served over Modbus over UDP by pymodbus's ``ModbusUdpServer`` (an independent
peer serving `peers.pattern`); both masters open the bus; it takes the unit ids of
``tcp://`` (0..255) and a socket's wire model, from its row of the transport table."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import pyrtu
from peers import pattern
from peers.tools import pymodbus_server

from pyrtu.poller import ConfigError, load_config, parse_config
from pyrtu.poller.masters import open_async_master, open_thread_master
from pyrtu.poller.plan import Wire

BUS = """[[bus]]
name = "drive"
port = "{port}"
timeout = 2.0
retries = 1

[[point]]
name = "drive.speed"
bus = "drive"
slave = {slave}
table = "holding"
address = 2
"""


@pytest.fixture(scope="module")
def udp_server() -> Iterator[int]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    with pymodbus_server(f"127.0.0.1:{port}", 1, mode="udp"):
        yield port


def test_poll_config_reads_a_udp_device(udp_server: int, tmp_path: Path) -> None:
    cfg = tmp_path / "points.toml"
    cfg.write_text(BUS.format(port=f"udp://127.0.0.1:{udp_server}", slave=255))
    r = pyrtu("poll", "--config", cfg, "--duration", "2", "--json", timeout=60)
    assert r.code == 0, (r.out, r.err)
    updates = [d for d in r.json_lines() if d.get("point") == "drive.speed" and "event" not in d]
    assert updates, r.out
    assert updates[0]["value"] == pattern.holding(1, 2)  # unit 255: the device itself


@pytest.mark.parametrize("opener", [open_async_master, open_thread_master])
def test_both_masters_open_a_udp_bus(udp_server: int, tmp_path: Path, opener: object) -> None:
    from pyrtu.pdu.requests import BY_FUNCTION

    cfg = tmp_path / "points.toml"
    cfg.write_text(BUS.format(port=f"udp://127.0.0.1:{udp_server}", slave=1))
    bus = load_config(cfg).bus("drive")
    assert bus.wire() == Wire.tcp()  # a socket's wire model, as tcp://

    async def main() -> list[int]:
        master = opener(bus)  # type: ignore[operator]
        try:
            value, _ = await master.transact(BY_FUNCTION[3], 255, 5, 2)
            return list(value)
        finally:
            await master.close()

    assert asyncio.run(main()) == pattern.holdings(1, 5, 2)


def test_unit_ids_and_bad_ports_name_the_line() -> None:
    for slave in (0, 255):
        parse_config(BUS.format(port="udp://127.0.0.1:5020", slave=slave), "p.toml")
    with pytest.raises(ConfigError, match=r"on a Modbus over UDP bus, not 256"):
        parse_config(BUS.format(port="udp://127.0.0.1:5020", slave=256), "p.toml")
    with pytest.raises(ConfigError, match=r"\(0\.\.255 on tcp://\), not 255"):
        parse_config(BUS.format(port="/dev/ttyUSB0", slave=255), "p.toml")  # a serial bus
    tls = BUS.format(port="udp://127.0.0.1:5020", slave=1).replace(
        "retries = 1", 'retries = 1\ntls_ca = "ca.crt"'
    )
    with pytest.raises(ConfigError, match="tls_ca: only an mbaps:// port takes TLS files"):
        parse_config(tls, "p.toml")


@pytest.mark.parametrize(
    ("port", "words"),
    [
        ("udp://plc:99999", "'udp://plc:99999': the port must be 0..65535"),
        ("udp://", "'udp://': expected udp://HOST[:PORT]"),
        ("tcp://plc:99999", "'tcp://plc:99999': the port must be 0..65535"),  # each URL's row
        ("rtu+tcp://:502", "'rtu+tcp://:502': expected rtu+tcp://HOST[:PORT]"),
    ],
)
def test_a_bad_url_is_a_config_error_at_its_line_exit_2(
    port: str, words: str, tmp_path: Path
) -> None:
    """Said by the bus's transport (`Transport.check_port`) when the file is read, at
    file:line: key, not found later as a port that is down (exit 3)."""
    cfg = tmp_path / "points.toml"
    cfg.write_text(BUS.format(port=port, slave=1))
    with pytest.raises(ConfigError) as info:
        load_config(cfg)
    assert str(info.value) == f'points.toml:3: bus[0] ("drive"): port: {words}'  # the port's line
    r = pyrtu("poll", "--config", cfg, "--duration", "1")
    assert r.code == 2 and r.out == "", (r.out, r.err)
    assert words in r.err and "Traceback" not in r.err
