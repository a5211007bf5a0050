"""Pytest fixtures of the interoperability peers (a plugin module).

Test modules load it with ``pytest_plugins = ["peers.fixtures"]`` (tests/ is on
sys.path under pytest's default import mode); the helpers are in `peers.tools`.

* `peer_binaries` (session): the libmodbus server and client compiled once into
  a temporary directory.  Without libmodbus-dev (or gcc, pkg-config) it FAILS with
  the command that installs them: CI installs them, and the interop matrix must
  not shrink silently.
* `pty_pair`: two pseudo-terminals joined by socat (fails without socat).
* `libmodbus_tcp`: a libmodbus TCP server (slave 1) on a free port, as a tcp:// URL.
* `silent_tcp`: a TCP server that accepts and reads but never answers (a dead device).
* `tcp_server`: a pymodbus and a libmodbus TCP server (slave 1, the register
  pattern), as a tcp:// URL and the requests it takes in flight.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator

import pytest

from .tools import (
    PeerBinaries,
    PeerBuildError,
    build_peers,
    free_tcp_port,
    libmodbus_server,
    pymodbus_server,
    socat_pair,
)

#: Requests a server takes in flight: pymodbus 3.16's TCP server answers only the
#: first of several ADUs that arrive in one read (found here; see tests/peers/README.md).
TCP_WINDOW = {"pymodbus": 1, "libmodbus": 8}


@pytest.fixture(scope="session")
def peer_binaries(tmp_path_factory: pytest.TempPathFactory) -> PeerBinaries:
    """The compiled libmodbus peers (fails, never skips, without libmodbus-dev)."""
    try:
        return build_peers(tmp_path_factory.mktemp("libmodbus-peers"))
    except PeerBuildError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture
def pty_pair() -> Iterator[tuple[str, str]]:
    """Two pseudo-terminal paths joined by socat."""
    try:
        with socat_pair() as pair:
            yield pair
    except PeerBuildError as exc:
        pytest.fail(str(exc), pytrace=False)


@pytest.fixture
def libmodbus_tcp(peer_binaries: PeerBinaries) -> Iterator[str]:
    """A libmodbus TCP server serving slave 1 on a free loopback port."""
    port = free_tcp_port()
    with libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1):
        yield f"tcp://127.0.0.1:{port}"


@pytest.fixture
def silent_tcp() -> Iterator[str]:
    """A server that accepts and reads but never answers: a dead device."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(8)
    held: list[socket.socket] = []

    def run() -> None:
        while True:
            try:
                held.append(listener.accept()[0])
            except OSError:
                return

    threading.Thread(target=run, daemon=True).start()
    yield f"tcp://127.0.0.1:{listener.getsockname()[1]}"
    listener.close()
    for s in held:
        s.close()


@pytest.fixture(params=["pymodbus", "libmodbus"])
def tcp_server(
    request: pytest.FixtureRequest, peer_binaries: PeerBinaries
) -> Iterator[tuple[str, int]]:
    """Each TCP server peer: (its tcp:// URL, the requests it takes in flight)."""
    port = free_tcp_port()
    if request.param == "pymodbus":
        peer = pymodbus_server(f"127.0.0.1:{port}", 1, mode="tcp")
    else:
        peer = libmodbus_server(peer_binaries, f"tcp:127.0.0.1:{port}", 1)
    with peer:
        yield f"tcp://127.0.0.1:{port}", TCP_WINDOW[request.param]
