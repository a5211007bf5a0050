"""``pyrtu simulate --tcp HOST:FIRST-LAST --metrics``: the ports of the range counted
as one server (issue 30, item 3)."""

from __future__ import annotations

import json
from pathlib import Path

from cli_helpers import Background, free_port_range
from metrics_helpers import health, sample, serving, until
from mqtt_broker import free_port

from pyrtu import Master

PORTS = 6
TEMPLATE = """\
[device]
vendor = "test"
model = "range"
address = 3

[[point]]
name = "a"
table = "holding"
address = 10
initial = 1234
"""


def test_metrics_add_up_the_ports(tmp_path: Path) -> None:
    template = tmp_path / "range.toml"
    template.write_text(TEMPLATE)
    address = f"127.0.0.1:{free_port()}"
    first = free_port_range(PORTS)
    spec = f"127.0.0.1:{first}-{first + PORTS - 1}"
    bg = Background(
        "simulate", "--template", template, "--tcp", spec, "--json", "--metrics", address
    )
    try:
        json.loads(bg.line(timeout=60))
        until(lambda: serving(address), "the metrics endpoint")
        masters = [Master(f"tcp://127.0.0.1:{first + i}", timeout=2.0) for i in (0, 3)]
        try:
            for m in masters:
                assert m.read_holding_registers(3, 10, 1) == [1234]
            assert sample(address, "pyrtu_simulate_tcp_requests_total") == 2
            assert sample(address, "pyrtu_simulate_tcp_clients_connected") == 2
            assert health(address)[0] == 200
        finally:
            for m in masters:
                m.close()
        until(lambda: sample(address, "pyrtu_simulate_tcp_clients_connected") == 0, "no client")
    finally:
        bg.kill()
