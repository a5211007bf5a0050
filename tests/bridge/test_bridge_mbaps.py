"""``pyrtu bridge`` on an ``mbaps://`` bus (#31.1): the bus's ``tls_cert``, ``tls_key``
and ``tls_ca`` (relative to the configuration file) reach a device behind pyrtu's
TLS listener, whose values arrive at a real mosquitto; a missing TLS key exits 2
naming file:line before anything connects."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from cli_helpers import kill_after_each_test
from mqtt_broker import Broker, Client
from tls_certs import Pki, make_pki

from pyrtu import DataStore
from pyrtu.security.tls import TlsListen, server_context
from pyrtu.tcp.server import TcpServer

STARTED: list[subprocess.Popen[str]] = []
_no_bridge_left = kill_after_each_test(STARTED)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def tls_server(pki: Pki) -> Iterator[tuple[DataStore, int]]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    store = DataStore()
    store.holding_registers.add_range(680, [1234, 5678])
    srv = TcpServer.for_store(1, store)
    tls = TlsListen("127.0.0.1", 0, server_context(pki.server.cert, pki.server.key, pki.ca.path))
    asyncio.run_coroutine_threadsafe(srv.start("127.0.0.1", 0, tls=tls), loop).result(30)
    assert srv.tls_address is not None
    yield store, srv.tls_address[1]
    asyncio.run_coroutine_threadsafe(srv.close(), loop).result(30)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


def write_config(folder: Path, pki: Pki, mqtt: str, port: str, tls: bool = True) -> Path:
    (folder / "pki").mkdir(exist_ok=True)
    for src, name in ((pki.operator.cert, "client.crt"), (pki.operator.key, "client.key"),
                      (pki.ca.path, "ca.crt")):  # fmt: skip
        (folder / "pki" / name).write_bytes(src.read_bytes())
    keys = 'tls_cert = "pki/client.crt"\ntls_key = "pki/client.key"\ntls_ca = "pki/ca.crt"\n'
    cfg = folder / "bridge.toml"
    cfg.write_text(f"""[mqtt]
url = "{mqtt}"
edge = "tls"

[[bus]]
name = "line"
port = "{port}"
timeout = 5.0
{keys if tls else ""}
[[point]]
name = "speed"
bus = "line"
slave = 1
table = "holding"
address = 680
interval = 0.1
""")
    return cfg


def test_bridge_publishes_an_mbaps_device(
    tls_server: tuple[DataStore, int], pki: Pki, tmp_path: Path
) -> None:
    store, port = tls_server
    with Broker(tmp_path) as broker, Client(broker, ["pyrtu/tls/#"]) as sub:
        cfg = write_config(tmp_path, pki, broker.url, f"mbaps://localhost:{port}")
        proc = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", "bridge", "--config", str(cfg), "--json"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd="/",
        )  # fmt: skip
        STARTED.append(proc)
        topic = "pyrtu/tls/line/1/speed"
        sub.wait(lambda: bool(sub.on(topic)), "a value read over mbaps://")
        proc.terminate()
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        assert json.loads(sub.on(topic)[0])["value"] == store.holding_registers.get(680) == 1234


def test_a_missing_tls_key_exits_2_naming_the_line(pki: Pki, tmp_path: Path) -> None:
    cfg = write_config(tmp_path, pki, "mqtt://127.0.0.1:1", "mbaps://localhost:802", tls=False)
    r = subprocess.run(
        [sys.executable, "-m", "pyrtu", "bridge", "--config", str(cfg)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    line = cfg.read_text().splitlines().index("[[bus]]") + 1
    assert r.returncode == 2, r.stderr
    assert f'bridge.toml:{line}: bus[0] ("line"): tls_cert: missing' in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
