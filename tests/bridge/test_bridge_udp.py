"""``pyrtu bridge`` on a ``udp://`` bus (#31.5): a device served over Modbus over UDP
by pymodbus's ``ModbusUdpServer`` (an independent peer serving `peers.pattern`), its
values published to a real mosquitto; a ``udp://`` URL the transport cannot open
exits 2 naming file:line before anything connects."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import kill_after_each_test
from mqtt_broker import Broker, Client
from peers import pattern
from peers.tools import pymodbus_server

STARTED: list[subprocess.Popen[str]] = []
_no_bridge_left = kill_after_each_test(STARTED)


@pytest.fixture(scope="module")
def udp_server() -> Iterator[int]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    with pymodbus_server(f"127.0.0.1:{port}", 1, mode="udp"):
        yield port


def write_config(folder: Path, mqtt: str, port: str) -> Path:
    cfg = folder / "bridge.toml"
    cfg.write_text(f"""[mqtt]
url = "{mqtt}"
edge = "udp"

[[bus]]
name = "line"
port = "{port}"
timeout = 2.0
retries = 1

[[point]]
name = "speed"
bus = "line"
slave = 1
table = "holding"
address = 680
interval = 0.1
""")
    return cfg


def test_bridge_publishes_a_udp_device(udp_server: int, tmp_path: Path) -> None:
    with Broker(tmp_path) as broker, Client(broker, ["pyrtu/udp/#"]) as sub:
        cfg = write_config(tmp_path, broker.url, f"udp://127.0.0.1:{udp_server}")
        proc = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", "bridge", "--config", str(cfg), "--json"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd="/",
        )  # fmt: skip
        STARTED.append(proc)
        topic = "pyrtu/udp/line/1/speed"
        sub.wait(lambda: bool(sub.on(topic)), "a value read over udp://")
        proc.terminate()
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert json.loads(sub.on(topic)[0])["value"] == pattern.holding(1, 680)


def test_a_bad_udp_url_exits_2_naming_the_line(tmp_path: Path) -> None:
    cfg = write_config(tmp_path, "mqtt://127.0.0.1:1", "udp://:502")
    r = subprocess.run(
        [sys.executable, "-m", "pyrtu", "bridge", "--config", str(cfg)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    line = cfg.read_text().splitlines().index('port = "udp://:502"') + 1
    assert r.returncode == 2, r.stderr
    assert f"bridge.toml:{line}: bus[0] (\"line\"): port: 'udp://:502': expected" in r.stderr
    assert "Traceback" not in r.stderr
