"""The sync ``mbaps://`` client's C path (csrc/rtu_tls_io.c over OpenSSL; issue 31):
the handshake in C against pyrtu's own TLS listener and against ``openssl s_server``
(Debian's openssl binary, an independent peer), for the handshake-level cases:
the server's certificate from another CA, naming another host (by name and by IP
address), expired; a TLS 1.1-only server refused; a server that never answers (the
handshake, or the request: each ends within its deadline); a reconnect that really
resumed the session (SSL_session_reused, and s_server saying so); answers byte for
byte as on ``tcp://``; and the build without OpenSSL (PYRTU_TLS=0) running
``mbaps://`` through the Python ssl fallback."""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import socket
import ssl
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from c_core import build_variant, missing
from tls_certs import DAY, NOW, Pair, Pki, make_pki

import pyrtu
from pyrtu import DataStore, NoResponseError, PortError
from pyrtu.core import _tls
from pyrtu.security.tls import TlsListen, client_context, server_context
from pyrtu.tcp import TcpClient
from pyrtu.tcp.server import TcpServer

ROOT = Path(__file__).resolve().parents[2]
OPENSSL = shutil.which("openssl")
needs_openssl = pytest.mark.skipif(OPENSSL is None, reason="needs Debian's openssl binary")


@pytest.fixture(autouse=True)
def c_tls(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Every test here runs the C path (its handshakes counted: a test that ended on
    the Python fallback fails), but the one about the build without it and the
    fallback's side of a comparison (``[python]``)."""
    if not _tls.available(pyrtu.backend("c") if "c" in pyrtu.available_backends() else pyrtu):
        missing("the C core's TLS (OpenSSL) is not built here")
    handshakes = []
    connect = _tls.CTlsContext.connect

    def counted(self: _tls.CTlsContext, fd: int, host: str, port: int, timeout: float) -> object:
        handshakes.append(host)
        return connect(self, fd, host, port, timeout)

    monkeypatch.setattr(_tls.CTlsContext, "connect", counted)
    yield
    if "without_openssl" not in request.node.name and "[python]" not in request.node.name:
        assert handshakes, "the C path did not run"


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"))


def operator(pki: Pki) -> ssl.SSLContext:
    return client_context(pki.operator.cert, pki.operator.key, pki.ca.path)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class SServer:
    """``openssl s_server`` on a free loopback port, requiring a client certificate
    signed by ``ca``; its standard input kept open (it sends nothing: a Modbus
    request is never answered); its output collected."""

    def __init__(self, cert: Pair, ca: Path, *extra: str) -> None:
        assert OPENSSL is not None
        self.port = free_port()
        cmd = [OPENSSL, "s_server", "-accept", f"127.0.0.1:{self.port}", "-cert", str(cert.cert),
               "-key", str(cert.key), "-CAfile", str(ca), "-Verify", "1", *extra]  # fmt: skip
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        deadline = time.monotonic() + 30
        while "ACCEPT" not in self.lines:
            assert self.proc.poll() is None, self.lines
            assert time.monotonic() < deadline, f"s_server did not start: {self.lines}"
            time.sleep(0.02)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            self.lines.append(raw.decode(errors="replace").rstrip("\n"))

    def stop(self) -> list[str]:
        self.proc.terminate()
        self.proc.wait(30)
        self._reader.join(10)
        return self.lines


@pytest.fixture
def listener(pki: Pki) -> Iterator[tuple[int, int]]:
    """pyrtu's `TcpServer` with a plain and a TLS listener on one store: (plain
    port, TLS port)."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    store = DataStore()
    store.holding_registers.add_range(0, [0x1234, 0xBEEF, 7, 0, 65535])
    store.input_registers.add_range(0, [1, 2, 3])
    store.coils.add_range(0, [True, False, True, True, False, False, True, False, True])
    srv = TcpServer.for_store(1, store)
    tls = TlsListen("127.0.0.1", 0, server_context(pki.server.cert, pki.server.key, pki.ca.path))
    asyncio.run_coroutine_threadsafe(srv.start("127.0.0.1", 0, tls=tls), loop).result(30)
    assert srv.address is not None and srv.tls_address is not None
    yield srv.address[1], srv.tls_address[1]
    asyncio.run_coroutine_threadsafe(srv.close(), loop).result(30)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


#: requests and the answers the Modbus Application Protocol (V1.1b3, section 6)
#: gives for the listener's store, built here with struct
EXCHANGES = [
    (bytes((3, 0, 0, 0, 2)), struct.pack(">BBHH", 3, 4, 0x1234, 0xBEEF)),
    (bytes((4, 0, 1, 0, 2)), struct.pack(">BBHH", 4, 4, 2, 3)),
    # coils 0..8: 1,0,1,1,0,0,1,0 | 1 -> 0b01001101, 0b00000001 (LSB first)
    (bytes((1, 0, 0, 0, 9)), struct.pack(">BBBB", 1, 2, 0b01001101, 0b00000001)),
    (bytes((6, 0, 3, 0xAB, 0xCD)), bytes((6, 0, 3, 0xAB, 0xCD))),  # an echo
    (bytes((3, 0, 3, 0, 1)), struct.pack(">BBH", 3, 2, 0xABCD)),
    (bytes((3, 0x10, 0, 0, 1)), bytes((0x83, 2))),  # illegal data address
    (bytes((0x41,)), bytes((0xC1, 1))),  # illegal function
]


def test_answers_byte_for_byte_as_on_tcp(listener: tuple[int, int], pki: Pki) -> None:
    plain_port, tls_port = listener
    context = operator(pki)
    plain = TcpClient(f"tcp://127.0.0.1:{plain_port}", timeout=5.0)
    secure = TcpClient(f"mbaps://localhost:{tls_port}", tls=context, timeout=5.0)
    fallback = TcpClient(
        f"mbaps://localhost:{tls_port}", tls=context, timeout=5.0, backend="python"
    )
    try:
        assert (secure.tls_path, fallback.tls_path, plain.tls_path) == ("c", "python", None)
        for request, expected in EXCHANGES:
            answers = [c.request(1, request, raw=True) for c in (plain, secure, fallback)]
            assert answers == [expected] * 3, request.hex()
        assert secure.counters == plain.counters == fallback.counters
    finally:
        for c in (plain, secure, fallback):
            c.close()


def test_many_transactions_on_one_connection(listener: tuple[int, int], pki: Pki) -> None:
    """Records one after the other (the read-ahead buffer, TLS 1.3's tickets read
    during the first answer): every answer the right one."""
    _, tls_port = listener
    with pyrtu.Master(f"mbaps://127.0.0.1:{tls_port}", tls=operator(pki), timeout=5.0) as m:
        for n in range(300):
            m.write_register(1, 3, n)
            assert m.read_holding_registers(1, 2, 2) == [7, n]


@pytest.mark.parametrize("version", ["TLSv1_2", "TLSv1_3"])
def test_reconnect_really_resumed_against_pyrtu(
    listener: tuple[int, int], pki: Pki, version: str
) -> None:
    _, tls_port = listener
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    context.maximum_version = ssl.TLSVersion[version]
    url = f"mbaps://localhost:{tls_port}"
    seen = []
    for _ in range(3):
        c = TcpClient(url, tls=context, timeout=5.0)
        assert c.tls_path == "c"
        assert c.request(1, bytes((3, 0, 2, 0, 1))) == bytes((3, 2, 0, 7))
        assert c._ctls is not None and c._ctls.version == version.replace("_", ".")
        seen.append(c.session_reused)
        c.close()
    assert seen == [False, True, True]
    from pyrtu.tcp.tls import forget_sessions

    forget_sessions(context)
    c = TcpClient(url, tls=context, timeout=5.0)
    try:
        assert not c.session_reused  # forgotten: a full handshake
    finally:
        c.close()


@needs_openssl
@pytest.mark.parametrize("version", ["-tls1_2", "-tls1_3"])
def test_reconnect_resumed_as_openssl_s_server_sees_it(pki: Pki, version: str) -> None:
    server = SServer(pki.server, pki.ca.path, version)
    try:
        url = f"mbaps://localhost:{server.port}"
        context = operator(pki)
        reused = []
        for _ in range(2):
            c = TcpClient(url, tls=context, timeout=0.5)
            reused.append(c.session_reused)
            with pytest.raises(NoResponseError):  # (s_server answers no Modbus; the
                c.request(1, bytes((3, 0, 0, 0, 1)))  # wait reads TLS 1.3's tickets)
            c.close()
    finally:
        lines = server.stop()
    assert reused == [False, True], lines
    # the server's own word: s_server prints this for a resumed handshake
    assert sum("Reused session-id" in line for line in lines) == 1, lines


@needs_openssl
@pytest.mark.parametrize(
    ("case", "pattern"),
    [
        ("other CA", r"TLS: the server.s certificate: unable to get local issuer certificate"),
        ("expired", r"TLS: the server.s certificate: certificate has expired"),
        ("name", r"TLS: the server.s certificate: hostname mismatch"),
        ("address", r"TLS: the server.s certificate: IP address mismatch"),
    ],
)
def test_the_server_certificate_refused(pki: Pki, case: str, pattern: str) -> None:
    if case == "other CA":
        cert = pki.other.issue("stranger-server", "localhost", server=True)
    elif case == "expired":
        cert = pki.ca.issue(
            "old-server", "localhost", server=True, before=NOW - 10 * DAY, after=NOW - DAY
        )
    else:  # names plc.example only (no IP address)
        cert = pki.ca.issue("plc-server", "plc.example", server=True, names=("plc.example",))
    server = SServer(cert, pki.ca.path)
    host = "127.0.0.1" if case == "address" else "localhost"
    try:
        with pytest.raises(PortError, match=pattern) as info:
            TcpClient(f"mbaps://{host}:{server.port}", tls=operator(pki), timeout=5.0)
        assert "cannot connect" in str(info.value)
    finally:
        server.stop()


@needs_openssl
def test_a_tls_1_1_only_server_is_refused(pki: Pki) -> None:
    server = SServer(pki.server, pki.ca.path, "-tls1_1", "-cipher", "DEFAULT@SECLEVEL=0")
    try:
        # the server does speak TLS 1.1 (openssl s_client, told to, gets through)
        assert OPENSSL is not None
        r = subprocess.run(
            [OPENSSL, "s_client", "-tls1_1", "-cipher", "DEFAULT@SECLEVEL=0",
             "-connect", f"127.0.0.1:{server.port}", "-cert", str(pki.operator.cert),
             "-key", str(pki.operator.key)],
            input=b"", capture_output=True, timeout=30, check=False,
        )  # fmt: skip
        assert b"TLSv1.1" in r.stdout, r.stdout[-2000:]
        with pytest.raises(PortError, match=r"TLS handshake failed: .*(protocol|version)"):
            TcpClient(f"mbaps://localhost:{server.port}", tls=operator(pki), timeout=5.0)
    finally:
        server.stop()


@pytest.mark.wall_clock
def test_a_server_that_never_handshakes_times_out_within_the_deadline(pki: Pki) -> None:
    """A listener whose kernel accepts the connection and which never says a word:
    the handshake ends at the connect timeout, not before, not much after."""
    with socket.socket() as mute:
        mute.bind(("127.0.0.1", 0))
        mute.listen(4)
        port = mute.getsockname()[1]
        start = time.monotonic()
        with pytest.raises(PortError, match=r"cannot connect: timed out after 0.5 s"):
            TcpClient(
                f"mbaps://localhost:{port}", tls=operator(pki), timeout=5.0, connect_timeout=0.5
            )
        elapsed = time.monotonic() - start
    assert 0.5 <= elapsed < 0.5 + 2.0, elapsed


@needs_openssl
@pytest.mark.wall_clock
def test_a_server_that_never_answers_times_out_within_the_deadline(pki: Pki) -> None:
    server = SServer(pki.server, pki.ca.path)
    try:
        with pyrtu.Master(
            f"mbaps://localhost:{server.port}", tls=operator(pki), timeout=0.4, retries=1
        ) as m:
            start = time.monotonic()
            with pytest.raises(NoResponseError):
                m.read_holding_registers(1, 0, 1)
            elapsed = time.monotonic() - start
    finally:
        lines = server.stop()
    # two attempts (retries=1) of 0.4 s each: the request was sent both times (s_server
    # prints what it received: the two MBAP requests' bytes, not parsed here)
    assert 0.8 <= elapsed < 0.8 + 2.0, elapsed
    assert any("ACCEPT" in line for line in lines)


def test_the_build_without_openssl_runs_mbaps_in_python(
    tmp_path: Path, pki: Pki, listener: tuple[int, int]
) -> None:
    """PYRTU_TLS=0 (as where OpenSSL's headers are missing): the C core builds without
    csrc/rtu_tls_io.c, and ``mbaps://`` runs over Python's ssl module."""
    if shutil.which(os.environ.get("CC", "cc")) is None:
        missing("no C compiler here")
    lib = build_variant(tmp_path, PYRTU_TLS="0")
    probe = f"""
import sys
sys.path.insert(0, {str(ROOT / "tests")!r})
import pyrtu
from pyrtu.core import _cext, _tls
from pyrtu.security.tls import client_context
from pyrtu.tcp import TcpClient
assert pyrtu.__file__.startswith({str(lib)!r}) and pyrtu.BACKEND == "c"
assert not hasattr(_cext.lib, "rtu_tls_ctx_new") and not _tls.available(_cext)
context = client_context(
    {str(pki.operator.cert)!r}, {str(pki.operator.key)!r}, {str(pki.ca.path)!r}
)
c = TcpClient("mbaps://localhost:{listener[1]}", tls=context, timeout=5.0)
assert c.tls_path == "python", c.tls_path
print(c.request(1, bytes((3, 0, 0, 0, 2))).hex())
c.close()
"""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYRTU_")}
    env.update(PYTHONPATH=str(lib), PYRTU_REQUIRE_C="1")
    run = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.strip() == struct.pack(">BBHH", 3, 4, 0x1234, 0xBEEF).hex()


class HalfRecordServer:
    """A TLS server (Python's ssl over memory BIOs, so that the test decides which
    bytes go on the wire): the handshake, the request read, then the answer's TLS
    record sent only in part (its first half) and nothing more; ``damaged``: the
    whole record instead, its last byte (of the AEAD tag) changed."""

    def __init__(self, pki: Pki, *, damaged: bool = False, then_handshake: bool = False) -> None:
        self.damaged = damaged
        #: a second connection after the first closes: its handshake alone, whether
        #: it resumed a session told by `resumed` (set once it is done)
        self.then_handshake = then_handshake
        self.resumed: bool | None = None
        self.context = server_context(pki.server.cert, pki.server.key, pki.ca.path)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self.listener.getsockname()[1]
        self.done = threading.Event()
        self.sent_half = threading.Event()
        self.handshaken = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _pump(self, conn: socket.socket, incoming: ssl.MemoryBIO, out: ssl.MemoryBIO) -> bool:
        conn.sendall(out.read())
        data = conn.recv(65536)
        incoming.write(data)
        return bool(data)

    def _handshake(
        self, conn: socket.socket
    ) -> tuple[ssl.SSLObject, ssl.MemoryBIO, ssl.MemoryBIO] | None:
        """A TLS connection on ``conn``, its handshake done (None: the client left)."""
        incoming, out = ssl.MemoryBIO(), ssl.MemoryBIO()
        tls = self.context.wrap_bio(incoming, out, server_side=True)
        while True:
            try:
                tls.do_handshake()
                return tls, incoming, out
            except ssl.SSLWantReadError:
                if not self._pump(conn, incoming, out):
                    return None

    def _serve(self) -> None:
        for first in (True, False):
            conn, _ = self.listener.accept()
            with conn:
                made = self._handshake(conn)
                if made is None:
                    return
                tls, incoming, out = made
                if not first:  # (then_handshake): the handshake alone
                    conn.sendall(out.read())
                    self.resumed = tls.session_reused
                    self.handshaken.set()
                    self.done.wait(30)
                    return
                if not self._answer_badly(conn, tls, incoming, out):
                    return
                if not self.then_handshake:
                    self.done.wait(30)
                    return
                conn.settimeout(30)
                with contextlib.suppress(OSError):
                    while conn.recv(65536):  # until the client closes
                        pass

    def _answer_badly(
        self, conn: socket.socket, tls: ssl.SSLObject, incoming: ssl.MemoryBIO, out: ssl.MemoryBIO
    ) -> bool:
        """Read the request, then send half of its answer's record, or all of it
        damaged; False if the client left first."""
        request = b""
        while len(request) < 12:  # a read of holding registers: 12 bytes of ADU
            try:
                request += tls.read(65536)
            except ssl.SSLWantReadError:
                if not self._pump(conn, incoming, out):
                    return False
        conn.sendall(out.read())
        tid = request[:2]  # the answer the Application Protocol gives (6.3)
        tls.write(tid + bytes((0, 0, 0, 5, 1, 3, 2, 0x12, 0x34)))
        record = out.read()
        if self.damaged:
            conn.sendall(record[:-1] + bytes((record[-1] ^ 0x01,)))
        else:
            conn.sendall(record[: len(record) // 2])
        self.sent_half.set()
        return True

    def close(self) -> None:
        self.done.set()
        self.thread.join(10)
        self.listener.close()


def test_a_fatal_alert_ends_the_session_a_broken_connection_does_not(pki: Pki) -> None:
    """A reconnect resumes the session of a connection that broke without a closure
    (RFC 5246 7.2.1; pyrtu marks its closure done: rtu_tls_close_notify), but not of
    one that ended in a fatal TLS alert: a record that fails its integrity check
    (bad_record_mac, RFC 8446 6.2).  The C path; both connections to one server
    context, whose tickets would resume."""
    for damaged, resumes in ((True, False), (False, True)):
        server = HalfRecordServer(pki, damaged=damaged, then_handshake=True)
        try:
            url = f"mbaps://localhost:{server.port}"
            c = TcpClient(url, tls=operator(pki), timeout=0.5, backend="c")
            try:
                assert c.tls_path == "c" and not c.session_reused
                with pytest.raises((PortError, NoResponseError)) as exc:
                    c.request(1, bytes((3, 0, 0, 0, 1)))
                assert ("bad record mac" in str(exc.value)) == damaged, exc.value
                if not damaged:  # half a record, then silence: the connection is given up
                    c._sock.shutdown(socket.SHUT_RDWR)
                    with pytest.raises(PortError):
                        c.request(1, bytes((3, 0, 0, 0, 1)))
                assert c.broken
                c.reconnect()
                assert server.handshaken.wait(10)
                assert c.session_reused == resumes and server.resumed == resumes
            finally:
                c.close()
        finally:
            server.close()


@pytest.mark.wall_clock
def test_half_a_record_then_silence_times_out_within_the_deadline(pki: Pki) -> None:
    """Part of the answer's TLS record is in OpenSSL's read-ahead buffer (there is
    something buffered, not a whole record): the client waits on the socket for the
    rest until the deadline, neither spinning past it nor answering early."""
    server = HalfRecordServer(pki)
    outcome: list[object] = []

    def client() -> None:
        c = TcpClient(f"mbaps://localhost:{server.port}", tls=operator(pki), timeout=0.5)
        try:
            start = time.monotonic()
            try:
                c.request(1, bytes((3, 0, 0, 0, 1)))
            except NoResponseError as exc:
                outcome.append(exc)
            outcome.append(time.monotonic() - start)
        finally:
            c.close()

    runner = threading.Thread(target=client, daemon=True)
    try:
        runner.start()
        runner.join(20)
        assert not runner.is_alive(), "the client did not give up at its deadline"
    finally:
        server.close()
    assert server.sent_half.is_set()
    assert isinstance(outcome[0], NoResponseError), outcome
    assert isinstance(outcome[1], float) and 0.5 <= outcome[1] < 0.5 + 2.0, outcome


@pytest.mark.parametrize("backend", ["c", "python"])
def test_a_damaged_record_is_reported_in_openssl_s_words(pki: Pki, backend: str) -> None:
    """An answer whose TLS record fails its integrity check ends the connection with
    OpenSSL's reason ("decryption failed or bad record mac", the text of
    SSL_R_DECRYPTION_FAILED_OR_BAD_RECORD_MAC), on the C path as on the Python ssl
    fallback: not the bare "Protocol error" of EPROTO."""
    server = HalfRecordServer(pki, damaged=True)
    try:
        c = TcpClient(
            f"mbaps://localhost:{server.port}", tls=operator(pki), timeout=5.0, backend=backend
        )
        try:
            assert c.tls_path == backend
            with pytest.raises(PortError, match="bad record mac") as exc:
                c.request(1, bytes((3, 0, 0, 0, 1)))
            assert "receive failed" in str(exc.value), exc.value
        finally:
            c.close()
    finally:
        server.close()
