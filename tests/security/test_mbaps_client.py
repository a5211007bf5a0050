"""``mbaps://`` on `pyrtu.Master`, `pyrtu.drivers.aio.AsyncMaster` and the TCP clients:
the client's certificate presented, the server's certificate and host name verified,
TLS 1.2 at least, the TLS session resumed on reconnect (the sync and the asyncio
client).  The server is pyrtu's TLS listener (test_tls_listener.py checks it against
independent clients)."""

from __future__ import annotations

import asyncio
import os
import socket
import ssl
import threading
from collections.abc import Iterator

import pytest
from c_core import missing
from tls_certs import Pki, make_pki

import pyrtu
from pyrtu import DataStore, Master, PortError
from pyrtu.core import _tls
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.security import parse_policy
from pyrtu.security.tls import TlsListen, client_context, server_context
from pyrtu.tcp import TcpClient
from pyrtu.tcp.server import TcpServer

POLICY = '[[rule]]\nroles = "operator"\n\n[[rule]]\nroles = "viewer"\nread_only = true\n'


@pytest.fixture(autouse=True, params=["c", "python"])
def tls_path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Every test on both paths of the sync client's TLS: the C core over OpenSSL
    (csrc/rtu_tls_io.c) and the Python ssl fallback (what runs where the C core was
    built without OpenSSL: `pyrtu.core._tls.accelerator` finds no C context)."""
    if request.param == "c":
        if not _tls.available(pyrtu.backend()):
            missing("the C core's TLS (OpenSSL) is not built here")
    else:
        monkeypatch.setattr(_tls, "accelerator", lambda context, backend: None)
    return str(request.param)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    return make_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def server(pki: Pki) -> Iterator[tuple[TcpServer, DataStore, int]]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    store = DataStore()
    store.holding_registers.add_range(0, list(range(100, 110)))
    srv = TcpServer.for_store(1, store, policy=parse_policy(POLICY, "p.toml"))
    tls = TlsListen("127.0.0.1", 0, server_context(pki.server.cert, pki.server.key, pki.ca.path))
    asyncio.run_coroutine_threadsafe(srv.start("127.0.0.1", 0, tls=tls), loop).result(30)
    assert srv.tls_address is not None
    yield srv, store, srv.tls_address[1]
    asyncio.run_coroutine_threadsafe(srv.close(), loop).result(30)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(10)
    loop.close()


def test_master_over_mbaps(server: tuple[TcpServer, DataStore, int], pki: Pki) -> None:
    _, store, port = server
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    with Master(f"mbaps://localhost:{port}", tls=context, timeout=5.0) as m:
        assert m.read_holding_registers(1, 0, 3) == [100, 101, 102]
        m.write_register(1, 4, 44)
        assert m.url == f"mbaps://localhost:{port}" and "TLS" in repr(m)
    assert store.holding_registers.get(4) == 44
    viewer = client_context(pki.viewer.cert, pki.viewer.key, pki.ca.path)
    with Master(f"mbaps://127.0.0.1:{port}", tls=viewer, timeout=5.0) as m:
        assert m.read_holding_registers(1, 4, 1) == [44]
        from pyrtu import ExceptionResponseError

        with pytest.raises(ExceptionResponseError) as info:
            m.write_register(1, 4, 45)
        assert info.value.code == 1
    assert store.holding_registers.get(4) == 44


def test_async_master_over_mbaps(server: tuple[TcpServer, DataStore, int], pki: Pki) -> None:
    _, _, port = server
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)

    async def main() -> list[list[int]]:
        async with AsyncMaster(f"mbaps://localhost:{port}", tls=context, timeout=5.0) as m:
            await m.write_registers(1, 0, [7, 8])
            return list(
                await asyncio.gather(*(m.read_holding_registers(1, a, 1) for a in range(4)))
            )

    assert asyncio.run(main()) == [[7], [8], [102], [103]]


def test_reconnect_resumes_the_tls_session(
    server: tuple[TcpServer, DataStore, int], pki: Pki, tls_path: str
) -> None:
    _, _, port = server
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    first = TcpClient(f"mbaps://localhost:{port}", tls=context, timeout=5.0)
    assert first.tls_path == tls_path
    assert first.request(1, bytes((3, 0, 0, 0, 1))) == bytes((3, 2, 0, 100))
    assert not first.session_reused
    first.close()
    again = TcpClient(f"mbaps://localhost:{port}", tls=context, timeout=5.0)
    try:
        assert again.session_reused  # an abbreviated handshake: the session resumed
        assert again.request(1, bytes((3, 0, 1, 0, 1))) == bytes((3, 2, 0, 101))
    finally:
        again.close()
    other = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    fresh = TcpClient(f"mbaps://localhost:{port}", tls=other, timeout=5.0)
    try:
        assert not fresh.session_reused  # sessions are kept per context
    finally:
        fresh.close()


def test_the_server_must_prove_its_name(server: tuple[TcpServer, DataStore, int], pki: Pki) -> None:
    _, _, port = server
    other_ca = client_context(pki.operator.cert, pki.operator.key, pki.other.path)
    with pytest.raises(
        PortError, match=r"TLS: the server.s certificate: (self-signed|unable to get local issuer)"
    ):
        Master(f"mbaps://localhost:{port}", tls=other_ca, timeout=5.0)
    # a server whose certificate names another host (its CA trusted)
    elsewhere = pki.ca.issue("elsewhere", "plc.example", server=True, names=("plc.example",))
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    srv = TcpServer.for_store(1, DataStore())
    context = server_context(elsewhere.cert, elsewhere.key, pki.ca.path)
    tls = TlsListen("127.0.0.1", 0, context)
    try:
        asyncio.run_coroutine_threadsafe(srv.start("127.0.0.1", 0, tls=tls), loop).result(30)
        assert srv.tls_address is not None
        client = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
        with pytest.raises(PortError, match=r"TLS: the server.s certificate: .*mismatch"):
            TcpClient(f"mbaps://127.0.0.1:{srv.tls_address[1]}", tls=client, timeout=5.0)
    finally:
        asyncio.run_coroutine_threadsafe(srv.close(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


def test_mbaps_needs_tls_and_tls_needs_mbaps(pki: Pki) -> None:
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    with pytest.raises(ValueError, match="tls: an mbaps:// port needs"):
        Master("mbaps://localhost:802")
    with pytest.raises(ValueError, match="tls: only an mbaps:// port"):
        Master("tcp://localhost:502", tls=context)
    with pytest.raises(TypeError, match=r"tls: .*not str"):
        Master("mbaps://localhost", tls="ca.pem")
    assert context.minimum_version >= ssl.TLSVersion.TLSv1_2 and context.check_hostname


def fail_under(sock: socket.socket) -> None:
    """The connection fails under its TLS layer (as when the network or the server
    goes): both directions of the socket shut through a descriptor of its own (an
    SSLSocket's own ``shutdown`` would drop its TLS object first)."""
    raw = socket.socket(fileno=os.dup(sock.fileno()))
    raw.shutdown(socket.SHUT_RDWR)
    raw.close()


def test_the_master_reconnects_resuming_the_tls_session(
    server: tuple[TcpServer, DataStore, int], pki: Pki, tls_path: str
) -> None:
    _, _, port = server
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    with Master(f"mbaps://localhost:{port}", tls=context, timeout=5.0) as m:
        assert m.read_holding_registers(1, 0, 1) == [100]
        client = m._link._client
        assert client.tls_path == tls_path and not client.session_reused
        fail_under(client._sock)
        with pytest.raises(PortError):
            m.read_holding_registers(1, 0, 1)
        assert m.read_holding_registers(1, 1, 1) == [101]  # a new connection
        assert client.session_reused and client.tls_path == tls_path
        assert m.counters["requests"] == 3 and m.counters["responses"] == 2


@pytest.mark.parametrize(
    "version", [ssl.TLSVersion.TLSv1_2, ssl.TLSVersion.TLSv1_3], ids=["TLSv1.2", "TLSv1.3"]
)
def test_the_asyncio_client_reconnects_resuming_the_tls_session(
    server: tuple[TcpServer, DataStore, int], pki: Pki, version: ssl.TLSVersion
) -> None:
    _, _, port = server
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    context.maximum_version = version

    async def main() -> None:
        async with AsyncMaster(f"mbaps://localhost:{port}", tls=context, timeout=5.0) as m:
            assert await m.read_holding_registers(1, 0, 1) == [100]
            client = m._link._client
            assert client is not None and not client.session_reused
            transport = client._conn.transport
            assert transport is not None
            fail_under(transport.get_extra_info("socket"))
            for _ in range(1000):  # the loop hears it (within 10 s)
                if client.broken:
                    break
                await asyncio.sleep(0.01)
            assert client.broken
            assert await m.read_holding_registers(1, 1, 1) == [101]  # reconnected
            assert m._link._client is client and client.session_reused
            ssl_object = client._conn.transport.get_extra_info("ssl_object")
            assert ssl_object.version() == version.name.replace("v1_", "v1.")
        # a second master with the same context resumes too (the sessions are the
        # context's, kept per host and port), one with another context does not
        async with AsyncMaster(f"mbaps://localhost:{port}", tls=context, timeout=5.0) as m:
            assert await m.read_holding_registers(1, 2, 1) == [102]
            assert m._link._client is not None and m._link._client.session_reused
        other = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
        async with AsyncMaster(f"mbaps://localhost:{port}", tls=other, timeout=5.0) as m:
            assert await m.read_holding_registers(1, 2, 1) == [102]
            assert m._link._client is not None and not m._link._client.session_reused

    asyncio.run(main())
