"""The TLS listener of `TcpServer` (MODBUS/TCP Security): mutual authentication, the
role from the certificate, the policy by role, and the attack matrix: every refused
handshake counted, said once, nothing executed, the other clients served.  Clients:
Python's `ssl` (blocking sockets), pymodbus's TLS client, and ``openssl s_client``
for the protocol versions Python's client no longer offers."""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
import ssl
import struct
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from tls_certs import Pair, Pki, make_pki
from waiting import wait_for

from pyrtu import DataStore
from pyrtu.gateway import GatewayLimits
from pyrtu.security import AuditTrail, Decision, Identity, parse_policy
from pyrtu.security.tls import TlsListen, TlsSetupError, certificate_role, server_context
from pyrtu.tcp.server import TcpServer

POLICY = """\
[[rule]]
roles = "operator"
units = "1"
holding_registers = "0-9"

[[rule]]
roles = ["viewer"]
read_only = true
"""


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"))


class Served:
    """A TcpServer with a plain and a TLS listener on a loop thread."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        pki: Pki,
        audit: AuditTrail | None = None,
        limits: GatewayLimits | None = None,
    ) -> None:
        self.loop = loop
        self.store = DataStore()
        self.store.holding_registers.add_range(0, list(range(100, 120)))
        self.denied: list[tuple[Identity, Decision]] = []
        self.server = TcpServer.for_store(
            1, self.store, limits, policy=parse_policy(POLICY, "p.toml"), audit=audit,
            on_denied=lambda who, why: self.denied.append((who, why)),
        )  # fmt: skip
        context = server_context(pki.server.cert, pki.server.key, pki.ca.path)
        tls = TlsListen("127.0.0.1", 0, context)
        self.call(self.server.start("127.0.0.1", 0, tls=tls))
        assert self.server.tls_address is not None and self.server.address is not None
        self.tls_port = self.server.tls_address[1]
        self.plain_port = self.server.address[1]

    def call(self, coro: object) -> object:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(30)  # type: ignore[arg-type]

    def stats(self) -> dict[str, object]:
        async def get() -> dict[str, object]:
            return self.server.stats()

        result = self.call(get())
        assert isinstance(result, dict)
        return result

    def wait(self, condition: Callable[[], bool], what: str) -> None:
        self.call(wait_for(condition, what, 30.0))

    def close(self) -> None:
        self.call(self.server.close())


@pytest.fixture
def served(loop: asyncio.AbstractEventLoop, pki: Pki) -> Iterator[Served]:
    s = Served(loop, pki)
    yield s
    s.close()


def client_context(pki: Pki, pair: Pair | None, ca: Path | None = None) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(cafile=str(ca or pki.ca.path))
    if pair is not None:
        context.load_cert_chain(str(pair.cert), str(pair.key))
    return context


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def recv_adu(sock: socket.socket) -> bytes:
    data = b""
    while len(data) < 7 or len(data) < 6 + struct.unpack(">H", data[4:6])[0]:
        chunk = sock.recv(300)
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


def tls_transact(
    port: int, context: ssl.SSLContext, requests: list[tuple[int, int, bytes]]
) -> list[bytes]:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as raw:
        with context.wrap_socket(raw, server_hostname="localhost") as s:
            answers = []
            for tid, unit, pdu in requests:
                s.sendall(mbap(tid, unit, pdu))
                answers.append(recv_adu(s))
            return answers


def refused(tid: int, unit: int, function: int) -> bytes:
    return struct.pack(">HHHBBB", tid, 0, 3, unit, function | 0x80, 1)


READ = struct.pack(">BHH", 3, 0, 2)
READ_ANSWER = struct.pack(">BBHH", 3, 4, 100, 101)


def test_the_role_of_a_certificate(pki: Pki) -> None:
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    def der(pair: Pair) -> bytes:
        cert = x509.load_pem_x509_certificate(pair.cert.read_bytes())
        return cert.public_bytes(serialization.Encoding.DER)

    assert certificate_role(der(pki.operator)) == ("operator", "CN=panel1")
    assert certificate_role(der(pki.no_role)) == (None, "CN=nobody")
    long = pki.ca.issue("long", "long", role="r" * 300)  # the long form of the length
    assert certificate_role(der(long)) == ("r" * 300, "CN=long")
    printable = pki.ca.issue("printable", "p", role=b"\x13\x02op")  # a PrintableString
    assert certificate_role(der(printable)) == (None, "CN=p")


def test_operator_role_gets_its_ranges_and_audit_names_it(
    loop: asyncio.AbstractEventLoop, pki: Pki, tmp_path: Path
) -> None:
    trail = AuditTrail.open(tmp_path / "audit.jsonl")
    served = Served(loop, pki, audit=trail)
    try:
        write9 = struct.pack(">BHH", 6, 9, 0x1234)
        write10 = struct.pack(">BHH", 6, 10, 0x1234)
        answers = tls_transact(
            served.tls_port, client_context(pki, pki.operator),
            [(1, 1, READ), (2, 1, write9), (3, 1, write10), (4, 2, READ)],
        )  # fmt: skip
        assert answers == [mbap(1, 1, READ_ANSWER), mbap(2, 1, write9), refused(3, 1, 6),
                           refused(4, 2, 3)]  # fmt: skip
        answers = tls_transact(
            served.tls_port, client_context(pki, pki.viewer), [(5, 1, READ), (6, 1, write9)]
        )
        assert answers == [mbap(5, 1, READ_ANSWER), refused(6, 1, 6)]
        assert served.store.holding_registers.get(9) == 0x1234
        assert served.store.holding_registers.get(10) == 110
        # the plain listener: no role, no rule for it
        with socket.create_connection(("127.0.0.1", served.plain_port), timeout=5) as s:
            s.sendall(mbap(7, 1, READ))
            assert recv_adu(s) == refused(7, 1, 3)
    finally:
        served.close()
        trail.close()
    (record,) = [json.loads(line) for line in (tmp_path / "audit.jsonl").read_text().splitlines()]
    assert (record["role"], record["subject"], record["address"], record["values"]) == (
        "operator", "CN=panel1", 9, [0x1234],
    )  # fmt: skip
    kinds = [(who.role, why.kind) for who, why in served.denied]
    assert kinds == [("operator", "address"), ("operator", "unit"), ("viewer", "read_only"),
                     (None, "no_rule")]  # fmt: skip


@pytest.mark.parametrize("case", ["no_role", "unknown_role"])
def test_a_certificate_without_a_known_role_gets_exception_01(
    served: Served, pki: Pki, case: str
) -> None:
    pair = getattr(pki, case)
    answers = tls_transact(served.tls_port, client_context(pki, pair), [(1, 1, READ)])
    assert answers == [refused(1, 1, 3)]
    ((who, why),) = served.denied
    assert why.kind == "no_rule" and who.role == (None if case == "no_role" else "admin")


def refused_handshake(port: int, context: ssl.SSLContext) -> str:
    """Connect, send a write, and see it fail: the error the client saw."""
    try:
        tls_transact(port, context, [(1, 1, struct.pack(">BHH", 6, 0, 0xDEAD))])
    except (ssl.SSLError, ConnectionError, OSError) as exc:
        return str(exc)
    raise AssertionError("the server answered a client it must refuse")


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("none", "CERTIFICATE"),  # no client certificate
        ("expired", "CERTIFICATE_VERIFY_FAILED"),
        ("not_yet_valid", "CERTIFICATE_VERIFY_FAILED"),
        ("self_signed", "CERTIFICATE_VERIFY_FAILED"),
        ("other_ca", "CERTIFICATE_VERIFY_FAILED"),
    ],
)
def test_a_client_certificate_the_listener_cannot_trust_is_refused(
    served: Served, pki: Pki, case: str, reason: str
) -> None:
    pair = None if case == "none" else getattr(pki, case)
    refused_handshake(served.tls_port, client_context(pki, pair))
    served.wait(lambda: served.server.counters["tls_failures"] == 1, "the refusal counted")
    assert served.store.holding_registers.get(0) == 100  # nothing executed
    ((_, why),) = served.denied
    assert why.kind == "tls_handshake" and reason in why.reason.upper().replace(" ", "_")
    # the others are served meanwhile
    assert tls_transact(served.tls_port, client_context(pki, pki.operator), [(2, 1, READ)]) == [
        mbap(2, 1, READ_ANSWER)
    ]
    stats = served.stats()
    assert stats["requests"] == 1 and stats["tls_failures"] == 1


def test_refusals_are_said_once_per_client_and_reason(served: Served, pki: Pki) -> None:
    for _ in range(3):
        refused_handshake(served.tls_port, client_context(pki, pki.expired))
    served.wait(lambda: served.server.counters["tls_failures"] == 3, "three refusals")
    assert len(served.denied) == 1


def test_the_client_checks_the_server(served: Served, pki: Pki) -> None:
    """An mbaps client verifies the server too: one trusting another CA refuses it."""
    context = client_context(pki, pki.operator, ca=pki.other.path)
    with pytest.raises(ssl.SSLCertVerificationError):
        tls_transact(served.tls_port, context, [(1, 1, READ)])


def test_plaintext_to_the_tls_port_and_tls_to_the_plain_port(served: Served, pki: Pki) -> None:
    with socket.create_connection(("127.0.0.1", served.tls_port), timeout=5) as s:
        s.sendall(mbap(1, 1, struct.pack(">BHH", 6, 0, 0xDEAD)))
        with pytest.raises(ConnectionError):
            recv_adu(s)
    served.wait(lambda: served.server.counters["tls_failures"] == 1, "the plaintext refused")
    context = client_context(pki, pki.operator)
    with socket.create_connection(("127.0.0.1", served.plain_port), timeout=5) as raw:
        with pytest.raises((ssl.SSLError, ConnectionError)):
            context.wrap_socket(raw, server_hostname="localhost")
    served.wait(lambda: served.server.counters["bad_headers"] == 1, "the hello refused")
    assert served.store.holding_registers.get(0) == 100
    assert served.server.counters["requests"] == 0


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs Debian's openssl")
@pytest.mark.parametrize("version", ["-tls1", "-tls1_1"])
def test_tls_1_0_and_1_1_are_refused(served: Served, pki: Pki, version: str) -> None:
    r = subprocess.run(
        ["openssl", "s_client", version, "-cipher", "DEFAULT@SECLEVEL=0",
         "-connect", f"127.0.0.1:{served.tls_port}", "-cert", str(pki.operator.cert),
         "-key", str(pki.operator.key), "-CAfile", str(pki.ca.path)],
        input="", capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert r.returncode != 0, r.stdout
    served.wait(lambda: served.server.counters["tls_failures"] == 1, "the old version refused")
    ((_, why),) = served.denied
    assert "PROTOCOL" in why.reason.upper() or "VERSION" in why.reason.upper(), why.reason
    # TLS 1.2 passes, through the same tool
    r = subprocess.run(
        ["openssl", "s_client", "-tls1_2", "-connect", f"127.0.0.1:{served.tls_port}",
         "-cert", str(pki.operator.cert), "-key", str(pki.operator.key),
         "-CAfile", str(pki.ca.path), "-verify_return_error"],
        input="", capture_output=True, text=True, timeout=30, check=False,
    )  # fmt: skip
    assert "Protocol  : TLSv1.2" in r.stdout or "TLSv1.2" in r.stdout, r.stdout + r.stderr


def test_64_handshakes_never_finished_hold_no_slot(
    loop: asyncio.AbstractEventLoop, pki: Pki
) -> None:
    """64 connections that open and never finish a handshake (half a ClientHello or
    nothing) in a table of 64: an operator is still served at once (a silent one
    gives way), and each is closed by the header timeout."""
    served = Served(loop, pki, limits=GatewayLimits(max_connections=64, header_timeout=2.0))
    stalled = []
    try:
        for n in range(64):
            s = socket.create_connection(("127.0.0.1", served.tls_port), timeout=5)
            if n % 2:
                s.sendall(b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03")  # half a hello
            stalled.append(s)
        served.wait(lambda: served.server.counters["connections"] == 64, "64 connections")
        answers = tls_transact(served.tls_port, client_context(pki, pki.operator), [(1, 1, READ)])
        assert answers == [mbap(1, 1, READ_ANSWER)]
        served.wait(
            lambda: (
                served.server.counters["header_timeouts"] + served.server.counters["evicted"] >= 64
            ),
            "every stalled handshake closed",
        )
        assert served.server.counters["evicted"] >= 1
    finally:
        for s in stalled:
            s.close()
        served.close()


def test_pymodbus_tls_client_against_the_tls_listener(served: Served, pki: Pki) -> None:
    from pymodbus.client import ModbusTlsClient

    context = client_context(pki, pki.operator)
    # pymodbus's sync TLS client wraps its socket without server_hostname: it cannot
    # check the host name (the CA still verifies the server's certificate)
    context.check_hostname = False
    client = ModbusTlsClient("localhost", port=served.tls_port, sslctx=context, timeout=2,
                             retries=0)  # fmt: skip
    try:
        assert client.connect()
        assert client.read_holding_registers(0, count=3, device_id=1).registers == [100, 101, 102]
        assert not client.write_register(5, 55, device_id=1).isError()
        rr = client.write_register(50, 1, device_id=1)
        assert rr.isError() and rr.exception_code == 1
    finally:
        client.close()
    assert served.store.holding_registers.get(5) == 55
    assert served.store.holding_registers.get(19) == 119


def test_setup_errors_name_the_option(pki: Pki, tmp_path: Path) -> None:
    with pytest.raises(TlsSetupError, match=r"--tls-cert .*: no such file"):
        server_context(tmp_path / "none.crt", pki.server.key, pki.ca.path)
    with pytest.raises(TlsSetupError, match=r"--tls-ca .*: not a CA certificate"):
        server_context(pki.server.cert, pki.server.key, pki.server.key)
    with pytest.raises(TlsSetupError, match=r"--tls-cert .*--tls-key"):
        server_context(pki.server.cert, pki.operator.key, pki.ca.path)  # not its key


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs Debian's openssl")
def test_a_renegotiation_is_refused(served: Served, pki: Pki) -> None:
    """``R`` in openssl s_client asks for a TLS 1.2 renegotiation: the listener never
    renegotiates (alert, connection closed), and serves the others meanwhile."""
    proc = subprocess.Popen(
        ["openssl", "s_client", "-tls1_2", "-connect", f"127.0.0.1:{served.tls_port}",
         "-cert", str(pki.operator.cert), "-key", str(pki.operator.key),
         "-CAfile", str(pki.ca.path)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert proc.stdin is not None and proc.stdout is not None
        while "Verify return code" not in (line := proc.stdout.readline()):
            assert line, "openssl s_client ended before its handshake"
        proc.stdin.write("R\n")
        proc.stdin.flush()
        served.wait(lambda: served.server.counters["tls_failures"] == 1, "the refusal")
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "RENEGOTIATING" in out and "no renegotiation" in out
    ((who, why),) = served.denied
    assert who.role == "operator" and why.reason.startswith("TLS: ")
    assert tls_transact(served.tls_port, client_context(pki, pki.operator), [(1, 1, READ)]) == [
        mbap(1, 1, READ_ANSWER)
    ]


def test_an_oversized_record_is_refused(served: Served, pki: Pki) -> None:
    """A handshake record longer than TLS allows (2^14 + 2048, RFC 5246 6.2.3): alert
    record_overflow (22, fatal), the connection closed, the refusal counted."""
    with socket.create_connection(("127.0.0.1", served.tls_port), timeout=5) as s:
        s.sendall(struct.pack(">BHH", 22, 0x0303, 2**14 + 2049) + b"\x01" * 64)
        alert = s.recv(64)
    assert alert[:1] == b"\x15" and alert[-2:] == bytes((2, 22)), alert.hex()  # fatal, overflow
    served.wait(lambda: served.server.counters["tls_failures"] == 1, "the refusal counted")
    assert served.server.counters["requests"] == 0
