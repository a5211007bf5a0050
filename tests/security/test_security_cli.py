"""``--policy``, ``--read-only`` and ``--audit`` on ``pyrtu gateway`` and ``pyrtu
simulate --tcp`` as programs: a policy with errors exits 2 naming file:line: key
before anything listens; a refused request is exception 01, one line per client
and reason, and never reaches the bus behind the gateway (the simulator's own
request counter says so); a listener beyond loopback with no policy says so once."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from peers.tools import peer_env

from pyrtu import ExceptionResponseError, pdu
from pyrtu.tcp import TcpClient

pytest_plugins = ["peers.fixtures"]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", *args],
        capture_output=True, text=True, timeout=60, env=peer_env(), check=False,
    )  # fmt: skip


def start(*args: str) -> tuple[subprocess.Popen[str], dict[str, object]]:
    """``pyrtu ARGS --json`` running; its first line (ready)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", *args, "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line, proc.stderr.read() if proc.stderr else ""
    return proc, json.loads(line)


def stop(proc: subprocess.Popen[str]) -> tuple[list[dict[str, object]], str]:
    """SIGTERM; its JSON lines and stderr (exit status 0)."""
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    return [json.loads(line) for line in out.splitlines()], err


@pytest.fixture
def procs() -> Iterator[list[subprocess.Popen[str]]]:
    started: list[subprocess.Popen[str]] = []
    yield started
    for p in started:
        if p.poll() is None:
            p.kill()
            p.communicate()


@pytest.mark.parametrize("command", ["gateway", "simulate"])
def test_a_policy_with_errors_exits_2_naming_file_line_and_key(
    command: str, tmp_path: Path
) -> None:
    policy = tmp_path / "plant.toml"
    policy.write_text(
        '[[rule]]\nclients = ["127.0.0.1"]\n\n[[rule]]\nroles = "op"\nunits = "1-300"\n'
    )
    if command == "gateway":
        args = ["gateway", "--listen", "127.0.0.1:0", "--port", "tcp://127.0.0.1:1"]
    else:
        args = ["simulate", "cfw100", "--tcp", "127.0.0.1:0"]
    r = run(*args, "--policy", str(policy))
    assert r.returncode == 2, r.stderr
    assert f"{policy}:6: rule[1]: units: expected unit ids 0..255" in r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    r = run(*args, "--policy", str(tmp_path / "none.toml"))
    assert r.returncode == 2 and "none.toml: no such file" in r.stderr


def test_simulate_policy_flags_need_tcp() -> None:
    r = run("simulate", "cfw100", "--port", "/dev/null", "--read-only")
    assert r.returncode == 2 and "--read-only" in r.stderr and "--tcp" in r.stderr


def test_gateway_policy_refuses_before_the_bus(
    procs: list[subprocess.Popen[str]], tmp_path: Path
) -> None:
    sim, ready = start("simulate", "cfw100", "--tcp", "127.0.0.1:0")
    procs.append(sim)
    policy = tmp_path / "policy.toml"
    policy.write_text(
        '[[rule]]\nname = "plant"\nclients = ["127.0.0.0/8"]\nunits = "1"\n'
        'holding_registers = "680-689"\n'
    )
    audit = tmp_path / "audit.jsonl"
    gw, gw_ready = start(
        "gateway", "--listen", "127.0.0.1:0", "--port", f"tcp://{ready['tcp']}=1",
        "--policy", str(policy), "--audit", str(audit),
    )  # fmt: skip
    procs.append(gw)
    with TcpClient(f"tcp://{gw_ready['listen']}", timeout=5.0) as c:
        c.request(1, pdu.write_register_request(683, 1234))  # allowed: the speed reference
        got = c.request(1, pdu.read_request(3, 683, 1))
        assert got is not None and pdu.parse_registers(got, 1) == [1234]
        for _ in range(3):  # outside the range: refused thrice, said once
            with pytest.raises(ExceptionResponseError) as info:
                c.request(1, pdu.write_register_request(690, 1))
            assert info.value.code == 1
        with pytest.raises(ExceptionResponseError) as info:
            c.request(1, pdu.read_request(1, 0, 1))  # coils: a table not named
        assert info.value.code == 1
    lines, _ = stop(gw)
    denied = [line for line in lines if line["type"] == "denied"]
    assert [(d["client"], d["kind"]) for d in denied] == [
        ("127.0.0.1", "address"),
        ("127.0.0.1", "table"),
    ]
    stopped = lines[-1]
    assert stopped["denied"] == 4 and stopped["denied_by"] == {"address": 3, "table": 1}
    assert stopped["audited_writes"] == 1
    sim_lines, _ = stop(sim)
    counters = sim_lines[-1]["counters"]
    assert isinstance(counters, dict)
    assert counters["requests"] == 2  # the write and the read: nothing refused got there
    (record,) = [json.loads(line) for line in audit.read_text().splitlines()]
    assert (record["function"], record["address"], record["values"], record["result"]) == (
        6, 683, [1234], "ok",
    )  # fmt: skip


def test_simulate_read_only_says_each_refusal_once(procs: list[subprocess.Popen[str]]) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "simulate", "cfw100", "--tcp", "127.0.0.1:0",
         "--read-only", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=peer_env(),
    )  # fmt: skip
    procs.append(proc)
    assert proc.stdout is not None
    ready = json.loads(proc.stdout.readline())
    with TcpClient(f"tcp://{ready['tcp']}", timeout=5.0) as c:
        before = pdu.parse_registers(c.request(1, pdu.read_request(3, 683, 1)) or b"", 1)
        for _ in range(2):
            with pytest.raises(ExceptionResponseError) as info:
                c.request(1, pdu.write_register_request(683, before[0] + 1))
            assert info.value.code == 1
        after = pdu.parse_registers(c.request(1, pdu.read_request(3, 683, 1)) or b"", 1)
        assert after == before
    lines, err = stop(proc)
    denied = [line for line in lines if line["type"] == "denied"]
    assert len(denied) == 1 and denied[0]["kind"] == "read_only"
    assert "warning" not in err


@pytest.mark.parametrize(("extra", "warned"), [((), True), (("--read-only",), False)])
def test_gateway_beyond_loopback_without_policy_says_so_once(
    extra: tuple[str, ...], warned: bool
) -> None:
    r = run("gateway", "--listen", "0.0.0.0:0", "--listen-rtu", "0.0.0.0:0", "--port",
            "tcp://127.0.0.1:1", "--duration", "0.5", *extra)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert r.stderr.count("with no access policy") == (1 if warned else 0), r.stderr


def test_gateway_on_loopback_says_nothing() -> None:
    r = run("gateway", "--listen", "127.0.0.1:0", "--port", "tcp://127.0.0.1:1",
            "--duration", "0.5")  # fmt: skip
    assert r.returncode == 0 and "access policy" not in r.stderr


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    from tls_certs import make_pki

    return make_pki(tmp_path_factory.mktemp("pki"))


def tls_options(pki) -> list[str]:  # type: ignore[no-untyped-def]
    return ["--tls-cert", str(pki.server.cert), "--tls-key", str(pki.server.key),
            "--tls-ca", str(pki.ca.path)]  # fmt: skip


@pytest.mark.parametrize("command", ["gateway", "simulate"])
def test_tls_option_errors_exit_2_naming_the_option(command: str, pki, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    if command == "gateway":
        base = ["gateway", "--listen", "127.0.0.1:0", "--port", "tcp://127.0.0.1:1"]
    else:
        base = ["simulate", "cfw100", "--tcp", "127.0.0.1:0"]
    cases = [
        (["--tls-listen", "127.0.0.1:0", "--tls-cert", str(pki.server.cert)],
         "--tls-listen needs --tls-key, --tls-ca"),
        (["--tls-ca", str(pki.ca.path)], "--tls-ca is for --tls-listen"),
        (["--tls-listen", "127.0.0.1:0", *tls_options(pki)[:-1], str(tmp_path / "no.pem")],
         "--tls-ca " + str(tmp_path / "no.pem") + ": no such file"),
        (["--tls-listen", "127.0.0.1:0", "--tls-cert", str(pki.server.cert), "--tls-key",
          str(pki.operator.key), "--tls-ca", str(pki.ca.path)], "not a certificate and its key"),
    ]  # fmt: skip
    for extra, said in cases:
        r = run(*base, *extra)
        assert r.returncode == 2 and said in r.stderr, (extra, r.stderr)
        assert "Traceback" not in r.stderr


def test_simulate_tls_listener_with_roles(
    procs: list[subprocess.Popen[str]], pki, tmp_path: Path
) -> None:  # type: ignore[no-untyped-def]
    import socket
    import ssl
    import struct

    policy = tmp_path / "roles.toml"
    policy.write_text(
        '[[rule]]\nroles = "operator"\n\n[[rule]]\nroles = "viewer"\nread_only = true\n'
    )
    proc, ready = start("simulate", "cfw100", "--tcp", "127.0.0.1:0", "--tls-listen",
                        "127.0.0.1:0", *tls_options(pki), "--policy", str(policy))  # fmt: skip
    procs.append(proc)
    host, port = str(ready["tls"]).rsplit(":", 1)

    def transact(pair, pdu_bytes: bytes) -> bytes:  # type: ignore[no-untyped-def]
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        context.load_verify_locations(cafile=str(pki.ca.path))
        context.load_cert_chain(str(pair.cert), str(pair.key))
        with socket.create_connection((host, int(port)), timeout=5) as raw:
            with context.wrap_socket(raw, server_hostname="localhost") as s:
                s.sendall(struct.pack(">HHHB", 9, 0, len(pdu_bytes) + 1, 1) + pdu_bytes)
                data = b""
                while len(data) < 7 or len(data) < 6 + struct.unpack(">H", data[4:6])[0]:
                    chunk = s.recv(300)
                    assert chunk
                    data += chunk
                return data[7:]

    write = struct.pack(">BHH", 6, 683, 1500)
    assert transact(pki.operator, write) == write  # [AP] 6.6: the echo
    assert transact(pki.viewer, struct.pack(">BHH", 6, 683, 1)) == bytes((0x86, 1))
    assert transact(pki.viewer, struct.pack(">BHH", 3, 683, 1)) == struct.pack(">BBH", 3, 2, 1500)
    lines, _ = stop(proc)
    (denied,) = [line for line in lines if line["type"] == "denied"]
    assert (denied["role"], denied["subject"], denied["kind"]) == (
        "viewer",
        "CN=screen",
        "read_only",
    )


def test_gateway_mbaps_bus_to_a_tls_listener(  # type: ignore[no-untyped-def]
    procs: list[subprocess.Popen[str]], pki, tmp_path: Path
) -> None:
    """gateway (plain) -> mbaps:// bus -> simulate's TLS listener: the gateway's client
    certificate carries the role the simulator's policy checks."""
    policy = tmp_path / "roles.toml"
    policy.write_text('[[rule]]\nroles = "operator"\nholding_registers = "680-689"\n')
    sim, ready = start("simulate", "cfw100", "--tcp", "127.0.0.1:0", "--tls-listen",
                       "127.0.0.1:0", *tls_options(pki), "--policy", str(policy))  # fmt: skip
    procs.append(sim)
    tls_port = str(ready["tls"]).rsplit(":", 1)[1]
    gw, gw_ready = start(
        "gateway", "--listen", "127.0.0.1:0", "--port", f"mbaps://localhost:{tls_port}=1",
        "--port-tls-cert", str(pki.operator.cert), "--port-tls-key", str(pki.operator.key),
        "--port-tls-ca", str(pki.ca.path), "--timeout", "3",
    )  # fmt: skip
    procs.append(gw)
    with TcpClient(f"tcp://{gw_ready['listen']}", timeout=5.0) as c:
        c.request(1, pdu.write_register_request(683, 900))
        got = c.request(1, pdu.read_request(3, 683, 1))
        assert got is not None and pdu.parse_registers(got, 1) == [900]
        with pytest.raises(ExceptionResponseError) as info:
            c.request(1, pdu.read_request(3, 0, 1))  # outside the role: the server's 01
        assert info.value.code == 1
    stop(gw)
    lines, _ = stop(sim)
    (denied,) = [line for line in lines if line["type"] == "denied"]
    assert (denied["role"], denied["subject"]) == ("operator", "CN=panel1")


def test_gateway_port_tls_options_need_an_mbaps_port(pki) -> None:  # type: ignore[no-untyped-def]
    r = run("gateway", "--listen", "127.0.0.1:0", "--port", "tcp://127.0.0.1:1",
            "--port-tls-ca", str(pki.ca.path))  # fmt: skip
    assert r.returncode == 2 and "--port-tls-ca is for an mbaps:// --port" in r.stderr
    r = run("gateway", "--listen", "127.0.0.1:0", "--port", "mbaps://127.0.0.1:1")
    assert r.returncode == 2 and "needs --port-tls-cert, --port-tls-key, --port-tls-ca" in r.stderr


def test_gateway_with_only_a_tls_listener(  # type: ignore[no-untyped-def]
    procs: list[subprocess.Popen[str]], pki
) -> None:
    """No --listen: the gateway listens for Modbus/TCP Security only (no plaintext
    port at all, not even on loopback); an mbaps:// client with a certificate the CA
    signed is served through it, and its ready line says there is no plain listener."""
    from pyrtu import Master
    from pyrtu.security.tls import client_context

    sim, ready = start("simulate", "cfw100", "--tcp", "127.0.0.1:0")
    procs.append(sim)
    gw, gw_ready = start("gateway", "--tls-listen", "127.0.0.1:0", *tls_options(pki),
                         "--port", f"tcp://{ready['tcp']}=1")  # fmt: skip
    procs.append(gw)
    assert gw_ready["listen"] is None and gw_ready["listen_rtu"] is None
    port = str(gw_ready["listen_tls"]).rsplit(":", 1)[1]
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    with Master(f"mbaps://localhost:{port}", tls=context, timeout=5.0) as m:
        m.write_register(1, 683, 1234)
        assert m.read_holding_registers(1, 683, 1) == [1234]
    stop(gw)


def test_gateway_with_no_listener_exits_2_naming_the_flags() -> None:
    r = run("gateway", "--port", "tcp://127.0.0.1:1")
    assert r.returncode == 2, r.stderr
    assert "give one of --listen, --tls-listen, --listen-rtu or --udp-listen" in r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
