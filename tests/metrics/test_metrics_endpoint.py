"""``--metrics`` scraped directly: each command's exposition (parsed by
prometheus_client's parser), ``/healthz`` going 503 with the reason when a port
goes away (a virtual bus's drop unplugged) and 200 when it is back, no password in
any output, and bad ``--metrics`` values refused before anything opens (exit 2,
one line naming ``--metrics``)."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from cli_helpers import ROOT, Background, env, pyrtu
from metrics_helpers import (
    BAUD,
    SERIAL,
    get,
    health,
    next_json,
    sample,
    samples,
    serving,
    stop,
    until,
    write_poll_config,
)
from mqtt_broker import Broker
from prometheus_server import free_port

from pyrtu import Master, ModbusError
from pyrtu.devices import CFW701Simulator
from pyrtu.metrics.address import MetricsError, parse_address
from pyrtu.metrics.histogram import BUCKETS, Latencies, family
from pyrtu.vbus import VirtualBus


def healthy(address: str) -> bool:
    return health(address)[0] == 200


# ---------------------------------------------------------------------- the option


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:1", ("127.0.0.1", 1)),  # the lowest port
        ("127.0.0.1:65535", ("127.0.0.1", 65535)),  # the highest
        ("[::1]:9100", ("::1", 9100)),
        ("localhost:9100", ("localhost", 9100)),
    ],
)
def test_addresses_accepted(text: str, expected: tuple[str, int]) -> None:
    assert parse_address(text) == expected


@pytest.mark.parametrize(
    "text", ["127.0.0.1:0", "127.0.0.1:65536", "9100", ":9100", "127.0.0.1:", "h:x", "::1:9100"]
)
def test_addresses_refused(text: str) -> None:
    with pytest.raises(MetricsError, match=r"^--metrics: "):
        parse_address(text)


#: each command, with arguments that would open a port that does not exist: the
#: --metrics error comes first (exit 2, not the port's 3)
COMMANDS: dict[str, list[str]] = {
    "poll": ["poll", "--config", "{config}"],
    "bridge": ["bridge", "--config", "{bridge}"],
    "gateway": ["gateway", "--listen", "127.0.0.1:0", "--port", "/dev/pyrtu-no-such-port"],
    "simulate": ["simulate", "cfw701", "--port", "/dev/pyrtu-no-such-port"],
}


def command_line(name: str, tmp_path: Path) -> list[str]:
    config = write_poll_config(tmp_path, "/dev/pyrtu-no-such-port")
    bridge = tmp_path / "bridge.toml"
    bridge.write_text(
        f'[mqtt]\nurl = "mqtt://127.0.0.1:1"\noutbox = "{tmp_path / "ob"}"\n'
        + config.read_text().replace("line1", "line")
    )
    return [a.format(config=config, bridge=bridge) for a in COMMANDS[name]]


@pytest.mark.parametrize("command", sorted(COMMANDS))
@pytest.mark.parametrize("value", ["127.0.0.1", "127.0.0.1:0", "127.0.0.1:70000", "[::1:9100"])
def test_a_bad_value_is_one_line_and_exit_2(tmp_path: Path, command: str, value: str) -> None:
    done = pyrtu(*command_line(command, tmp_path), "--metrics", value, "--duration", "1")
    assert done.code == 2, done.err
    (line,) = done.err.splitlines()
    assert line.startswith(f"pyrtu {command}: error: --metrics") and value in line, line


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_port_in_use_is_exit_2_before_anything_opens(tmp_path: Path, command: str) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = pyrtu(*command_line(command, tmp_path), "--metrics", f"127.0.0.1:{port}", "-d", "1")
    assert done.code == 2, done.err
    (line,) = done.err.splitlines()
    assert line.startswith(f"pyrtu {command}: error: --metrics: cannot listen on 127.0.0.1:{port}")
    assert "in use" in line


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_client_missing_names_the_extra(tmp_path: Path, command: str) -> None:
    """prometheus_client hidden (an import that fails, as where it is not installed)."""
    code = (
        "import sys; sys.modules['prometheus_client'] = None\n"
        "from pyrtu.cli import main\n"
        f"sys.exit(main({[*command_line(command, tmp_path), '--metrics', '127.0.0.1:9']!r}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env(), capture_output=True, text=True,
        timeout=30,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.splitlines()
    assert "--metrics" in line and "pip install 'pyrtu[metrics]'" in line, line


# ---------------------------------------------------------------------- histograms


def test_a_latency_on_a_bucket_bound_counts_in_that_bucket() -> None:
    """Prometheus buckets are "less than or equal": 5 ms exactly is in le="0.005"."""
    latencies = Latencies()
    latencies.observe("a", 1, 0.005)
    latencies.observe("a", 1, 0.005000001)
    latencies.observe("a", 1, 100.0)
    (metric,) = [family("x_seconds", "x", latencies.snapshot())]
    buckets = {s.labels["le"]: s.value for s in metric.samples if s.name == "x_seconds_bucket"}
    assert buckets["0.0025"] == 0 and buckets["0.005"] == 1 and buckets["0.01"] == 2
    assert buckets[repr(BUCKETS[-1])] == 2 and buckets["+Inf"] == 3
    count = next(s.value for s in metric.samples if s.name == "x_seconds_count")
    total = next(s.value for s in metric.samples if s.name == "x_seconds_sum")
    assert count == 3 and total == pytest.approx(100.010000001)


# ---------------------------------------------------------------------- each command


def test_poll_health_goes_503_when_its_port_is_unplugged(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        config = write_poll_config(tmp_path, bus.paths[0])
        poll = Background("poll", "--config", config, "--json", "--metrics", address)
        try:
            until(lambda: serving(address), "the endpoint")
            until(lambda: (sample(address, "pyrtu_poll_responses_total", bus="line1",
                                  slave="1") or 0) >= 5, "answers")  # fmt: skip
            assert health(address) == (200, "ok\n")
            assert get(f"http://{address}/")[0] == 200
            assert get(f"http://{address}/nothing")[0] == 404
            bus.unplug(0)  # the poller's own adapter pulled out
            until(lambda: not healthy(address), "503")
            status, body = health(address)
            assert status == 503 and f"bus line1: port {bus.paths[0]} down" in body, body
            port = {"bus": "line1", "port": bus.paths[0]}
            assert sample(address, "pyrtu_poll_port_up", **port) == 0
            assert sample(address, "pyrtu_poll_port_outages_total", bus="line1") == 1
            assert sample(address, "pyrtu_healthy") == 0
            bus.replug(0)
            until(lambda: healthy(address), "200 again")
            assert sample(address, "pyrtu_poll_port_up", **port) == 1
        finally:
            code = stop(poll)
            sim.close()
    assert code == 0


def test_gateway_health_goes_503_when_a_bus_is_unplugged() -> None:
    address = f"127.0.0.1:{free_port()}"
    with VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        gateway = Background(
            "gateway", "--listen", "127.0.0.1:0", "--port", bus.paths[0], *SERIAL,
            "--json", "--metrics", address,
        )  # fmt: skip
        try:
            listen = next_json(gateway, "ready")["listen"]
            until(lambda: serving(address), "the endpoint")
            assert health(address) == (200, "ok\n")
            with Master(f"tcp://{listen}", timeout=2.0) as master:
                for _ in range(7):
                    master.read_holding_registers(1, 680, 1)
                got = samples(address)
                assert got[("pyrtu_gateway_clients_connected", frozenset())] == 1
            on_bus = frozenset({("bus", bus.paths[0])})
            assert got[("pyrtu_gateway_bus_transactions_total", on_bus)] == 7
            assert got[("pyrtu_gateway_requests_total", frozenset())] == 7
            bus.unplug(0)
            with Master(f"tcp://{listen}", timeout=2.0) as master:  # the bus fails in use
                for _ in range(3):
                    with contextlib.suppress(ModbusError):
                        master.read_holding_registers(1, 680, 1)
            until(lambda: not healthy(address), "503")
            status, body = health(address)
            assert status == 503 and f"bus {bus.paths[0]} down" in body, body
            assert sample(address, "pyrtu_gateway_bus_up", bus=bus.paths[0]) == 0
            bus.replug(0)
            until(lambda: healthy(address), "200 again")
        finally:
            code = stop(gateway)
            sim.close()
    assert code == 0


def test_simulate_health_goes_503_when_its_port_is_unplugged() -> None:
    address = f"127.0.0.1:{free_port()}"
    with VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        simulate = Background(
            "simulate", "cfw701", "--port", bus.paths[1], *SERIAL, "--json", "--metrics", address
        )
        try:
            next_json(simulate, "ready")
            until(lambda: serving(address), "the endpoint")
            with Master(bus.paths[0], baudrate=BAUD, parity="N", timeout=0.5) as master:
                for _ in range(9):
                    master.read_holding_registers(1, 680, 1)
            assert sample(address, "pyrtu_simulate_requests_total") == 9
            assert sample(address, "pyrtu_simulate_responses_total") == 9
            assert sample(address, "pyrtu_simulate_port_up", port=bus.paths[1]) == 1
            assert health(address) == (200, "ok\n")
            bus.unplug(1)  # the simulator's own drop
            until(lambda: not healthy(address), "503")
            status, body = health(address)
            assert status == 503 and f"port {bus.paths[1]} down" in body, body
            assert sample(address, "pyrtu_simulate_port_up", port=bus.paths[1]) == 0
            bus.replug(1)
            until(lambda: healthy(address), "200 again")
        finally:
            code = stop(simulate)
    assert code == 0


PASSWORD = "pw-Nq7-never-shown"


def test_bridge_exposition_health_and_no_password(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with (
        Broker(tmp_path, users={"edge": PASSWORD}) as broker,
        VirtualBus(2, baudrate=BAUD, parity="N") as bus,
    ):
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        secret = tmp_path / "mqtt.pass"
        secret.write_text(PASSWORD + "\n")
        config = tmp_path / "bridge.toml"
        poll = write_poll_config(tmp_path, bus.paths[0]).read_text()
        config.write_text(
            f'[mqtt]\nurl = "{broker.url}"\nedge = "e1"\noutbox = "{tmp_path / "ob"}"\n'
            f'username = "edge"\npassword_file = "{secret}"\nbackoff = 0.1\nmax_backoff = 0.3\n'
            + poll
        )
        bridge = Background("bridge", "--config", config, "--metrics", address, "--drain", "0")
        try:
            until(lambda: serving(address), "the endpoint")
            until(lambda: sample(address, "pyrtu_bridge_broker_connected") == 1, "connected")
            until(lambda: (sample(address, "pyrtu_bridge_acknowledged_total") or 0) > 0, "acks")
            until(lambda: healthy(address), "healthy")
            got = samples(address)
            assert got[("pyrtu_bridge_outbox_depth", frozenset())] >= 0
            assert got[("pyrtu_poll_points", frozenset({("bus", "line1")}))] == 5
            body = get(f"http://{address}/metrics")[1] + health(address)[1]
            broker.stop()
            until(lambda: not healthy(address), "503")
            status, text = health(address)
            assert status == 503 and f"broker 127.0.0.1:{broker.port} not connected" in text, text
            body += text + get(f"http://{address}/metrics")[1]
            for hidden in (PASSWORD, str(secret)):
                assert hidden not in body
        finally:
            code = stop(bridge)
            sim.close()
    assert PASSWORD not in "".join(bridge.err) + "".join(bridge.out)
    assert code == 0


# ---------------------------------------------------------------------- supervision


class Quiet:
    """A source with nothing wrong and nothing to say."""

    def collect(self) -> list[Any]:
        return []

    def health(self) -> list[str]:
        return []


def test_the_http_server_that_fails_is_reported_and_started_again() -> None:
    from pyrtu.drivers.supervise import TaskFailure
    from pyrtu.metrics.server import MetricsServer

    reports: list[TaskFailure] = []
    port = free_port()
    server = MetricsServer("127.0.0.1", port, "test", report=reports.append)
    real = server._httpd.serve_forever
    calls = 0

    def fails_once(poll_interval: float = 0.5) -> None:
        nonlocal calls
        calls += 1
        if calls == 1:
            raise RuntimeError("the first serve_forever breaks")
        real(poll_interval)

    server._httpd.serve_forever = fails_once  # type: ignore[method-assign]
    try:
        server.serve(Quiet())
        until(lambda: serving(f"127.0.0.1:{port}"), "served again after the failure")
        assert health(f"127.0.0.1:{port}") == (200, "ok\n")
        (failure,) = reports
        assert failure.task == "pyrtu-metrics-http" and failure.first
        assert failure.cause == "RuntimeError: the first serve_forever breaks"
        assert calls == 2
    finally:
        server.close()
    with socket.create_server(("127.0.0.1", port)):  # the port is released
        pass
