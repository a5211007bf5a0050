"""``--metrics`` scraped by a real Prometheus (Debian's ``prometheus``, started on a
free loopback port, stopped by pid): each command's endpoint is a target, and the
values Prometheus stored (its HTTP API, ``/api/v1/query``) are checked against
what the test itself did: the reads a simulator answered (its own counters), the
requests a client sent, a simulator stopped, a broker killed."""

from __future__ import annotations

from pathlib import Path

import pytest
from bridge_configs import mqtt_table, weg_on_line
from cli_helpers import Background
from metrics_helpers import BAUD, SERIAL, next_json, serving, stop, until, write_poll_config
from mqtt_broker import Broker, Client
from prometheus_server import Prometheus, free_port

from pyrtu import Master
from pyrtu.devices import CFW701Simulator
from pyrtu.poller import profile_points
from pyrtu.vbus import VirtualBus


def test_the_poller_scraped_counts_what_the_simulator_answered(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        slave = sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        config = write_poll_config(tmp_path, bus.paths[0])
        poll = Background("poll", "--config", config, "--json", "--metrics", address)
        try:
            until(lambda: serving(address), "the endpoint")
            with Prometheus(tmp_path, [address]) as prom:
                line = '{bus="line1",slave="1"}'
                scraped = prom.wait(f"pyrtu_poll_responses_total{line}", lambda v: v >= 20, "20")
                answered = slave.counters["responses"]  # the simulator's own account
                assert scraped <= answered
                # every answer was a transaction on the bus and one latency observed
                prom.wait('pyrtu_poll_transactions_total{bus="line1"}', lambda v: v >= 20, "20")
                observed = prom.wait(
                    f"pyrtu_poll_latency_seconds_count{line}", lambda v: v >= 20, "20 latencies"
                )
                assert observed <= slave.counters["responses"]
                prom.wait(
                    "pyrtu_poll_errors_total{kind='timeout',bus='line1'}", lambda v: v == 0, "it"
                )
                prom.wait('pyrtu_poll_points_stale{bus="line1"}', lambda v: v == 0, "it")
                prom.wait("pyrtu_healthy", lambda v: v == 1, "it")
                prom.wait('up{job="pyrtu"}', lambda v: v == 1, "it")

                sim.close()  # the drive goes silent: timeouts, offline, every point stale
                prom.wait(
                    "pyrtu_poll_errors_total{kind='timeout',bus='line1'}",
                    lambda v: v >= 2,
                    "timeouts",
                )
                points = len(profile_points("cfw701", "weg", "line1", 1, 0.05))
                prom.wait(
                    'pyrtu_poll_points_stale{bus="line1"}', lambda v: v == points, "stale points"
                )
                prom.wait(f"pyrtu_poll_slave_online{line}", lambda v: v == 0, "offline")
                # a silent slave is no fault of the command: its port and tasks are up
                prom.wait('pyrtu_poll_port_up{bus="line1"}', lambda v: v == 1, "it")
                prom.wait("pyrtu_healthy", lambda v: v == 1, "it")
        finally:
            code = stop(poll)
            sim.close()
    assert code == 4  # slave 1 offline at the end


def test_the_gateway_scraped_counts_the_client_requests(tmp_path: Path) -> None:
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
            with Prometheus(tmp_path, [address]) as prom:
                master = Master(f"tcp://{listen}", timeout=2.0)
                try:
                    for _ in range(30):
                        master.read_holding_registers(1, 680, 1)
                    prom.wait("pyrtu_gateway_requests_total", lambda v: v == 30, "30 requests")
                    prom.wait("pyrtu_gateway_clients_connected", lambda v: v == 1, "one client")
                finally:
                    master.close()
                on_bus = f'{{bus="{bus.paths[0]}"}}'
                prom.wait(f"pyrtu_gateway_bus_transactions_total{on_bus}", lambda v: v == 30, "it")
                prom.wait("pyrtu_gateway_answers_total", lambda v: v == 30, "it")
                latency = f'pyrtu_gateway_latency_seconds_count{{bus="{bus.paths[0]}",slave="1"}}'
                prom.wait(latency, lambda v: v == 30, "it")
                prom.wait('pyrtu_gateway_errors_total{kind="timeout"}', lambda v: v == 0, "it")
                prom.wait("pyrtu_gateway_clients_connected", lambda v: v == 0, "no client")
                prom.wait("pyrtu_healthy", lambda v: v == 1, "it")
        finally:
            code = stop(gateway)
            sim.close()
    assert code == 0


def test_simulate_tcp_scraped_counts_requests_and_clients(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    simulate = Background(
        "simulate", "cfw701", "--tcp", "127.0.0.1:0", "--json", "--metrics", address
    )
    try:
        tcp = next_json(simulate, "ready")["tcp"]
        with Prometheus(tmp_path, [address]) as prom:
            first, second = Master(f"tcp://{tcp}", timeout=2.0), Master(f"tcp://{tcp}", timeout=2.0)
            try:
                for _ in range(25):
                    first.read_holding_registers(1, 680, 1)
                second.read_holding_registers(1, 680, 1)
                prom.wait("pyrtu_simulate_tcp_requests_total", lambda v: v == 26, "26 requests")
                prom.wait("pyrtu_simulate_tcp_clients_connected", lambda v: v == 2, "two clients")
                prom.wait("pyrtu_simulate_tcp_connections_total", lambda v: v == 2, "it")
            finally:
                first.close()
                second.close()
            prom.wait("pyrtu_simulate_tcp_clients_connected", lambda v: v == 0, "no client")
            prom.wait("pyrtu_healthy", lambda v: v == 1, "it")
    finally:
        code = stop(simulate)
    assert code == 0


def bridge_config(url: str, outbox: Path, port: str, sparkplug: bool = False) -> str:
    """The bridge's configuration (``sparkplug``: in Sparkplug B mode): the CFW701
    polled every 50 ms, its values published at least every 0.2 s (``max_age``),
    the broker's user "edge" with its password."""
    login = f'username = "edge"\npassword = "{PASSWORD}"\n'
    spb = '[sparkplug]\ngroup_id = "plant1"\n' if sparkplug else ""
    line = weg_on_line(port, 0.05, "offline_after = 2\n")
    return f"[defaults]\nmax_age = 0.2\n{mqtt_table(url, outbox, login)}{spb}{line}"


#: the MQTT password: in no label, no value, no health line
PASSWORD = "s3cret-Zq81"


def broker_killed(prom: Prometheus, broker: Broker, *zero: str) -> None:
    """The broker killed: what Prometheus stores says disconnected (and each of
    ``zero`` 0), a backlog in the outbox (values published at least every 0.2 s
    pile up) that ages, unhealthy; the password in none of its series."""
    broker.kill()
    prom.wait("pyrtu_bridge_broker_connected", lambda v: v == 0, "disconnected")
    for name in zero:
        prom.wait(name, lambda v: v == 0, f"{name} 0")
    prom.wait("pyrtu_bridge_outbox_depth", lambda v: v >= 10, "a backlog")
    prom.wait("pyrtu_bridge_outbox_oldest_age_seconds", lambda v: v >= 0.5, "its age")
    prom.wait("pyrtu_healthy", lambda v: v == 0, "unhealthy")
    stored = prom.query('{job="pyrtu"}')
    assert stored and all(
        PASSWORD not in key and PASSWORD not in value
        for labels, _ in stored
        for key, value in labels.items()
    )


def test_the_bridge_scraped_outbox_and_broker(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with (
        Broker(tmp_path, users={"edge": PASSWORD}) as broker,
        VirtualBus(2, baudrate=BAUD, parity="N") as bus,
    ):
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        config = tmp_path / "bridge.toml"
        config.write_text(bridge_config(broker.url, tmp_path / "ob", bus.paths[0]))
        bridge = Background("bridge", "--config", config, "--metrics", address, "--drain", "0")
        try:
            until(lambda: serving(address), "the endpoint")
            with Prometheus(tmp_path, [address]) as prom:
                prom.wait("pyrtu_bridge_broker_connected", lambda v: v == 1, "connected")
                prom.wait("pyrtu_bridge_acknowledged_total", lambda v: v >= 5, "acknowledged")
                prom.wait('pyrtu_poll_responses_total{slave="1"}', lambda v: v >= 5, "polled")
                prom.wait("pyrtu_healthy", lambda v: v == 1, "it")
                broker_killed(prom, broker)
        finally:
            code = stop(bridge)
            sim.close()
    assert code == 0
    assert PASSWORD not in "".join(bridge.err)


def test_the_sparkplug_edge_node_scraped_births_data_and_outbox(tmp_path: Path) -> None:
    """``pyrtu bridge`` with ``[sparkplug]``: the births Prometheus stored are the
    ones a subscriber of the broker received; the broker killed: disconnected, not
    born, a backlog that ages, unhealthy; the password in no series."""
    pytest.importorskip("google.protobuf", reason="protobuf is not installed (pyrtu[sparkplug])")
    address = f"127.0.0.1:{free_port()}"
    watcher_password = "w4tch-Pq2"
    with (
        Broker(tmp_path, users={"edge": PASSWORD, "watcher": watcher_password}) as broker,
        VirtualBus(2, baudrate=BAUD, parity="N") as bus,
    ):
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        watcher = Client(broker, ["spBv1.0/#"], username="watcher", password=watcher_password)
        config = tmp_path / "bridge.toml"
        config.write_text(bridge_config(broker.url, tmp_path / "ob", bus.paths[0], sparkplug=True))
        node = Background("bridge", "--config", config, "--metrics", address)
        try:
            until(lambda: serving(address), "the endpoint")
            with Prometheus(tmp_path, [address]) as prom:
                prom.wait("pyrtu_sparkplug_born", lambda v: v == 1, "born")
                births = "spBv1.0/plant1/{}/e1"
                prom.wait(
                    'pyrtu_sparkplug_messages_total{type="NBIRTH"}',
                    lambda v: v == len(watcher.on(births.format("NBIRTH"))) == 1,
                    "the NBIRTH the watcher received",
                )
                prom.wait(
                    'pyrtu_sparkplug_messages_total{type="DBIRTH"}',
                    lambda v: v == len(watcher.on(births.format("DBIRTH") + "/weg")) >= 1,
                    "the DBIRTH the watcher received",
                )
                prom.wait('pyrtu_sparkplug_messages_total{type="DDATA"}', lambda v: v >= 3, "data")
                prom.wait('pyrtu_sparkplug_device_alive{device="weg"}', lambda v: v == 1, "it")
                prom.wait('pyrtu_poll_responses_total{slave="1"}', lambda v: v >= 5, "polled")
                prom.wait("pyrtu_healthy", lambda v: v == 1, "healthy")
                broker_killed(prom, broker, "pyrtu_sparkplug_born")
        finally:
            code = stop(node)
            watcher.close()
            sim.close()
    assert code == 0, node.err
    assert PASSWORD not in "".join(node.err)
