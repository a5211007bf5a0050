"""Interop with tmodbus (PyPI), an independent Modbus/TCP Security implementation with
roles, in both directions: tmodbus's client against pyrtu's TLS listener, pyrtu's
``mbaps://`` master against tmodbus's TLS server.  tmodbus needs Python >= 3.12: it
runs in a virtual environment of its own (build/tmodbus/, made once with pip, kept
between runs), its side scripted in tests/security/tmodbus_side/."""

from __future__ import annotations

import asyncio
import glob
import json
import shutil
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from tls_certs import Pki, make_pki

from pyrtu import DataStore, ExceptionResponseError, Master
from pyrtu.security import parse_policy
from pyrtu.security.tls import TlsListen, client_context, server_context
from pyrtu.tcp.server import TcpServer

ROOT = Path(__file__).resolve().parents[2]
PEERS = Path(__file__).resolve().parent / "tmodbus_side"
TMODBUS = "tmodbus[security]==1.1.0"
HOME = ROOT / "build" / "tmodbus"


def _python312() -> str | None:
    """A Python >= 3.12 interpreter of this machine that runs, or None (pyenv's shims
    exist for versions that are not selected: each candidate is tried)."""
    candidates = [shutil.which(name) for name in ("python3.14", "python3.13", "python3.12")]
    candidates += sorted(glob.glob("/root/.pyenv/versions/3.1[2-9]*/bin/python3"), reverse=True)
    for candidate in filter(None, candidates):
        probe = subprocess.run(
            [candidate, "-c", "import sys; assert sys.version_info >= (3, 12)"],
            capture_output=True, timeout=60, check=False,
        )  # fmt: skip
        if probe.returncode == 0:
            return candidate
    return None


@pytest.fixture(scope="module")
def tmodbus() -> str:
    """The python of the tmodbus environment (made when missing)."""
    python = HOME / "bin" / "python"
    marker = HOME / ".installed"
    if python.exists() and marker.exists() and marker.read_text() == TMODBUS:
        return str(python)
    base = _python312()
    if base is None:
        pytest.skip("tmodbus needs Python >= 3.12; none is installed here")
    subprocess.run([base, "-m", "venv", "--clear", str(HOME)], check=True, timeout=300)
    done = subprocess.run(
        [str(python), "-m", "pip", "install", "--disable-pip-version-check", "-q", TMODBUS],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert done.returncode == 0, f"pip could not install {TMODBUS}: {done.stderr}"
    marker.write_text(TMODBUS)
    return str(python)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def pyrtu_server(pki: Pki) -> Iterator[tuple[DataStore, int]]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    store = DataStore()
    store.holding_registers.add_range(0, [100 + a for a in range(10)])
    policy = parse_policy('[[rule]]\nroles = "operator"\n\n[[rule]]\nroles = "viewer"\n'
                          "read_only = true\n", "roles.toml")  # fmt: skip
    server = TcpServer.for_store(1, store, policy=policy)
    tls = TlsListen("127.0.0.1", 0, server_context(pki.server.cert, pki.server.key, pki.ca.path))
    asyncio.run_coroutine_threadsafe(server.start("127.0.0.1", 0, tls=tls), loop).result(30)
    assert server.tls_address is not None
    yield store, server.tls_address[1]
    asyncio.run_coroutine_threadsafe(server.close(), loop).result(30)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


def tmodbus_client(
    python: str, port: int, pki: Pki, who: str, ops: list[list[object]]
) -> list[dict[str, object]]:
    pair = getattr(pki, who)
    done = subprocess.run(
        [python, str(PEERS / "tmodbus_client.py"), "localhost", str(port), str(pair.cert),
         str(pair.key), str(pki.ca.path), json.dumps(ops)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()]


def test_tmodbus_client_against_pyrtu_tls_listener(
    tmodbus: str, pyrtu_server: tuple[DataStore, int], pki: Pki
) -> None:
    store, port = pyrtu_server
    ops: list[list[object]] = [["read", 0, 3], ["write", 2, 77], ["read", 2, 1]]
    assert tmodbus_client(tmodbus, port, pki, "operator", ops) == [
        {"ok": [100, 101, 102]}, {"ok": True}, {"ok": [77]},
    ]  # fmt: skip
    assert tmodbus_client(tmodbus, port, pki, "viewer", [["read", 2, 1], ["write", 2, 1]]) == [
        {"ok": [77]}, {"exception": "IllegalFunctionError"},
    ]  # fmt: skip
    assert tmodbus_client(tmodbus, port, pki, "no_role", [["read", 0, 1]]) == [
        {"exception": "IllegalFunctionError"}
    ]
    assert store.holding_registers.get(2) == 77


def test_pyrtu_master_against_tmodbus_tls_server(tmodbus: str, pki: Pki) -> None:
    proc = subprocess.Popen(
        [tmodbus, str(PEERS / "tmodbus_server.py"), str(pki.server.cert), str(pki.server.key),
         str(pki.ca.path)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line, proc.stderr.read() if proc.stderr else ""
        port = json.loads(line)["port"]

        def master(who: str) -> Master:
            pair = getattr(pki, who)
            tls = client_context(pair.cert, pair.key, pki.ca.path)
            return Master(f"mbaps://localhost:{port}", tls=tls, timeout=5.0)

        with master("operator") as m:
            assert m.read_holding_registers(1, 0, 3) == [100, 101, 102]
            m.write_register(1, 2, 77)
        with master("viewer") as m:
            assert m.read_holding_registers(1, 2, 1) == [77]
            with pytest.raises(ExceptionResponseError) as info:
                m.write_register(1, 2, 1)
            assert info.value.code == 1
        with master("no_role") as m, pytest.raises(ExceptionResponseError) as info:
            m.read_holding_registers(1, 0, 1)
        assert info.value.code == 1
    finally:
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    writes = [json.loads(x) for x in out.splitlines()]
    assert writes == [{"wrote": [2, 77], "role": "operator"}], err
