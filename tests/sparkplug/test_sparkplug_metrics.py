"""``pyrtu bridge --metrics HOST:PORT`` in Sparkplug B mode: the edge node run by
the CLI against a real mosquitto and a simulated drive on the virtual bus, its
``/metrics`` scraped over HTTP and parsed by prometheus_client's own parser, its
counters checked against what the broker carried to a host application written
from the specification (sparkplug_host.py: its own protobuf decoder) and against
the drive's own registers; ``/healthz`` while the broker runs and after it is
stopped; the MQTT password in no scrape; a bad ``--metrics`` a usage error."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from bridge_configs import BAUD, mqtt_table, vbus, weg_on_line
from cli_helpers import ROOT, Background, env, pyrtu
from mqtt_broker import Broker, free_port
from sparkplug_host import Host, encode_metric, encode_payload

pytest.importorskip("google.protobuf", reason="protobuf is not installed (pyrtu[sparkplug])")
pytest.importorskip("prometheus_client", reason="pip install 'pyrtu[metrics]'")

from metrics_helpers import get, sample, samples, serving, until

from pyrtu.devices import CFW701Simulator, weg

GROUP, EDGE = "plant1", "e1"
#: the MQTT password: in no label, no value, no health line, no message
PASSWORD = "spb-Kx93-never-shown"

#: the bus's outages: offline after three missed polls of 0.5 s
OUTAGES = "offline_after = 3\nbackoff = 0.1\nmax_backoff = 0.4\n"


def write_config(
    tmp: Path, url: str, port: str, credentials: str = "", sparkplug: str = ""
) -> Path:
    path = tmp / "b.toml"
    mqtt = mqtt_table(url, tmp / "ob", f"fsync_interval = 0.05\n{credentials}\n", EDGE)
    path.write_text(f"""{mqtt}
[sparkplug]
group_id = "{GROUP}"
{sparkplug}

{weg_on_line(port, 0.05, OUTAGES, timeout=0.5)}
[[point]]
name = "weg.ref"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_REFERENCE}
writable = true
min = 0
max = 8192
interval = 0.05
""")
    return path


def messages(address: str, kind: str) -> float | None:
    return sample(address, "pyrtu_sparkplug_messages_total", type=kind)


def segments(outbox: Path) -> int:
    """The bytes of the outbox's segment files, as the file system has them."""
    return sum(path.stat().st_size for path in outbox.glob("*.seg"))


def stop(bg: Background) -> int:
    bg.proc.send_signal(signal.SIGINT)
    return bg.finish(timeout=30).code


def test_the_edge_node_scraped_counts_what_the_broker_carried(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with Broker(tmp_path) as broker, vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        host = Host(broker)
        node = Background(
            "bridge", "--config", write_config(tmp_path, broker.url, bus.paths[0]),
            "--metrics", address,
        )  # fmt: skip
        try:
            until(lambda: serving(address), "the endpoint")
            host.wait(lambda: host.of("NBIRTH") and host.of("DBIRTH", "weg"), "the births")
            # the births: as many as the host received, the bdSeq the NBIRTH carried
            until(lambda: messages(address, "DBIRTH") == len(host.of("DBIRTH")), "DBIRTHs")
            got = samples(address)
            assert got[("pyrtu_sparkplug_messages_total", frozenset({("type", "NBIRTH")}))] == 1
            (nbirth,) = host.of("NBIRTH")
            bdseq = {m.name: m for m in nbirth.decoded().metrics}["bdSeq"].raw
            assert got[("pyrtu_sparkplug_bdseq", frozenset())] == bdseq
            assert got[("pyrtu_sparkplug_born", frozenset())] == 1
            assert got[("pyrtu_bridge_broker_connected", frozenset())] == 1
            assert got[("pyrtu_bridge_broker_connections_total", frozenset())] == 1
            assert got[("pyrtu_sparkplug_device_alive", frozenset({("device", "weg")}))] == 1
            info = frozenset({("group_id", GROUP), ("edge_node_id", EDGE)})
            assert got[("pyrtu_sparkplug_node_info", info)] == 1
            (served,) = [dict(labels) for name, labels in got if name == "pyrtu_info"]
            assert served["command"] == "bridge"
            assert got[("pyrtu_poll_points", frozenset({("bus", "line")}))] >= 1
            assert get(f"http://{address}/healthz") == (200, "ok\n")
            assert got[("pyrtu_healthy", frozenset())] == 1
            listed = (ROOT / "docs" / "METRICS.md").read_text(encoding="utf-8")
            for name in {n for n, _ in got if n.startswith(("pyrtu_sparkplug", "pyrtu_bridge"))}:
                assert f"`{name}`" in listed, f"{name} is not in docs/METRICS.md"

            # commands: two refused by the node, one through the set path to the drive
            dcmd = f"spBv1.0/{GROUP}/DCMD/{EDGE}"
            one = encode_payload(encode_metric(name="ref", value_field="int_value", value=1000))
            host.command(f"{dcmd}/nobody", one)
            nope = encode_metric(name="nope", value_field="int_value", value=1)
            host.command(f"{dcmd}/weg", encode_payload(nope))
            host.command(f"{dcmd}/weg", one)
            until(lambda: sim.get(weg.P_REFERENCE) == 1000, "the write on the drive")
            refused = "pyrtu_sparkplug_commands_refused_total"
            until(lambda: sample(address, refused, reason="unknown_device") == 1, "refused")
            until(lambda: sample(address, refused, reason="unknown_metric") == 1, "refused")
            executed = "pyrtu_bridge_commands_total"
            until(lambda: sample(address, executed, result="executed") == 1, "executed")
            assert sample(address, executed, result="received") == 1
            assert sample(address, refused, reason="validation") == 0

            # a Rebirth asked for: NBIRTH and the DBIRTH again
            rebirth = encode_metric(name="Node Control/Rebirth", value=True)
            host.command(f"spBv1.0/{GROUP}/NCMD/{EDGE}", encode_payload(rebirth))
            host.wait(lambda: len(host.of("NBIRTH")) == 2, "the second NBIRTH")
            until(lambda: sample(address, "pyrtu_sparkplug_rebirths_total") == 1, "a rebirth")
            until(lambda: messages(address, "NBIRTH") == 2, "two NBIRTHs")
            until(lambda: messages(address, "DBIRTH") == len(host.of("DBIRTH")) >= 2, "DBIRTHs")

            # the drive silent: its DDEATH, then no more data: every DDATA and metric
            # the host received is counted, and the broker confirmed every record
            sim.close()
            host.wait(lambda: host.of("DDEATH", "weg"), "the DDEATH")
            until(lambda: messages(address, "DDEATH") == len(host.of("DDEATH")), "DDEATHs")
            alive = ("pyrtu_sparkplug_device_alive", frozenset({("device", "weg")}))
            until(lambda: samples(address)[alive] == 0, "the device dead")
            ddata = host.of("DDATA", "weg")
            assert ddata  # the values the drive answered (and the write read back)
            decoded = [m for msg in ddata for m in msg.decoded().metrics]
            historical = sum(1 for m in decoded if m.is_historical)
            published = "pyrtu_sparkplug_metrics_published_total"
            until(lambda: messages(address, "DDATA") == len(host.of("DDATA")), "the DDATA")
            until(lambda: sample(address, published, kind="live") == len(decoded) - historical,
                  "the live metrics")  # fmt: skip
            assert sample(address, published, kind="historical") == historical
            until(lambda: sample(address, "pyrtu_bridge_outbox_depth") == 0, "all confirmed")
            assert sample(address, "pyrtu_bridge_outbox_oldest_age_seconds") == 0
            until(lambda: sample(address, "pyrtu_bridge_outbox_bytes") == segments(tmp_path / "ob"),
                  "the outbox's size")  # fmt: skip
            assert segments(tmp_path / "ob") > 0  # the segment being written
            for name in (
                "pyrtu_sparkplug_unforwarded_total",
                "pyrtu_sparkplug_foreign_records_total",
                "pyrtu_bridge_outbox_dropped_total",
                "pyrtu_bridge_task_failures_total",
            ):
                assert sample(address, name) == 0, name
            # a silent slave is no fault of the node
            assert get(f"http://{address}/healthz") == (200, "ok\n")

            broker.stop()  # by pid
            until(lambda: get(f"http://{address}/healthz")[0] == 503, "503")
            status, text = get(f"http://{address}/healthz")
            assert status == 503 and f"broker 127.0.0.1:{broker.port} not connected" in text, text
            until(lambda: sample(address, "pyrtu_bridge_broker_connected") == 0, "disconnected")
            until(lambda: sample(address, "pyrtu_bridge_broker_outages_total") == 1, "an outage")
            got = samples(address)
            assert got[("pyrtu_sparkplug_born", frozenset())] == 0
            assert got[("pyrtu_healthy", frozenset())] == 0
        finally:
            code = stop(node)
            host.close()
            sim.close()
    assert code == 0, node.err
    assert "Traceback" not in "".join(node.err)


def test_the_password_is_in_no_scrape_and_no_health_line(tmp_path: Path) -> None:
    address = f"127.0.0.1:{free_port()}"
    with (
        Broker(tmp_path, users={"edge": PASSWORD}) as broker,
        vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus,
    ):
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        secret = tmp_path / "mqtt.pass"
        secret.write_text(PASSWORD + "\n")
        credentials = f'username = "edge"\npassword_file = "{secret}"'
        config = write_config(tmp_path, broker.url, bus.paths[0], credentials)
        node = Background("bridge", "--config", config, "--metrics", address)
        try:
            until(lambda: serving(address), "the endpoint")
            # born: the broker took the password
            until(lambda: sample(address, "pyrtu_sparkplug_born") == 1, "born")
            until(lambda: (messages(address, "DDATA") or 0) > 0, "data")
            bodies = [get(f"http://{address}/metrics")[1], get(f"http://{address}/healthz")[1]]
            broker.stop()
            until(lambda: get(f"http://{address}/healthz")[0] == 503, "503")
            bodies += [get(f"http://{address}/metrics")[1], get(f"http://{address}/healthz")[1]]
        finally:
            code = stop(node)
            sim.close()
    assert code == 0, node.err
    said = "".join(bodies) + "".join(node.err) + "".join(node.out)
    assert "pyrtu_sparkplug_messages_total" in said and "not connected" in said
    for hidden in (PASSWORD, str(secret)):
        assert hidden not in said


def test_health_says_the_node_waits_for_its_primary_host(tmp_path: Path) -> None:
    """With ``primary_host_id``: connected, not born while the host has said nothing
    or says offline (503 naming it), born and healthy while it says online."""
    address = f"127.0.0.1:{free_port()}"
    with Broker(tmp_path) as broker, vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        host = Host(broker, "scada")
        config = write_config(
            tmp_path, broker.url, bus.paths[0], sparkplug='primary_host_id = "scada"'
        )
        node = Background("bridge", "--config", config, "--metrics", address)
        waits = "primary host scada offline: the node waits to be born"
        try:
            until(lambda: serving(address), "the endpoint")
            until(lambda: sample(address, "pyrtu_bridge_broker_connected") == 1, "connected")
            until(lambda: waits in get(f"http://{address}/healthz")[1], "the host named")
            assert get(f"http://{address}/healthz")[0] == 503
            assert sample(address, "pyrtu_sparkplug_born") == 0
            assert messages(address, "NBIRTH") == 0 and not host.of("NBIRTH")
            host.state(True)
            host.wait(lambda: host.of("NBIRTH"), "the NBIRTH")
            until(lambda: get(f"http://{address}/healthz") == (200, "ok\n"), "healthy")
            assert sample(address, "pyrtu_sparkplug_born") == 1
            host.state(False)
            until(lambda: sample(address, "pyrtu_sparkplug_host_offline_total") == 1, "counted")
            until(lambda: waits in get(f"http://{address}/healthz")[1], "waiting again")
            assert sample(address, "pyrtu_sparkplug_born") == 0
        finally:
            code = stop(node)
            host.close()
            sim.close()
    assert code == 0, node.err


@pytest.mark.parametrize("value", ["127.0.0.1", "127.0.0.1:0", "127.0.0.1:70000", "[::1:9100"])
def test_a_bad_metrics_value_exits_2_naming_it_before_anything_opens(
    tmp_path: Path, value: str
) -> None:
    config = write_config(tmp_path, "mqtt://127.0.0.1:1", "/dev/pyrtu-no-such-port")
    done = pyrtu("bridge", "--config", config, "--metrics", value, "--duration", "1")
    assert done.code == 2, done.err
    (line,) = done.err.splitlines()
    assert line.startswith("pyrtu bridge: error: --metrics") and value in line, line
    assert not (tmp_path / "ob").exists()  # no outbox made
    assert not (tmp_path / "ob.bdseq").exists()  # no bdSeq taken


def test_a_metrics_port_in_use_exits_2_before_anything_opens(tmp_path: Path) -> None:
    config = write_config(tmp_path, "mqtt://127.0.0.1:1", "/dev/pyrtu-no-such-port")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = pyrtu("bridge", "--config", config, "--metrics", f"127.0.0.1:{port}", "-d", "1")
    assert done.code == 2, done.err
    (line,) = done.err.splitlines()
    assert line.startswith(f"pyrtu bridge: error: --metrics: cannot listen on 127.0.0.1:{port}")
    assert not (tmp_path / "ob").exists() and not (tmp_path / "ob.bdseq").exists()


def test_without_the_prometheus_client_the_extra_is_named(tmp_path: Path) -> None:
    """prometheus_client hidden (an import that fails, as where it is not installed):
    exit 2, one line naming ``--metrics`` and the extra, nothing opened."""
    config = write_config(tmp_path, "mqtt://127.0.0.1:1", "/dev/pyrtu-no-such-port")
    argv = ["bridge", "--config", str(config), "--metrics", "127.0.0.1:9", "-d", "1"]
    code = (
        "import sys; sys.modules['prometheus_client'] = None\n"
        "from pyrtu.cli import main\n"
        f"sys.exit(main({argv!r}))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env(), capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.splitlines()
    assert "--metrics" in line and "pip install 'pyrtu[metrics]'" in line, line
    assert not (tmp_path / "ob").exists()
