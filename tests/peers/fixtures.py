"""Pytest fixtures of the interoperability peers (a plugin module).

Test modules load it with ``pytest_plugins = ["peers.fixtures"]`` (tests/ is on
sys.path under pytest's default import mode); the helpers are in `peers.tools`.

* `peer_binaries` (session): the libmodbus server and client compiled once into
  a temporary directory.  Without libmodbus-dev (or gcc, pkg-config) it FAILS with
  the command that installs them: CI installs them, and the interop matrix must
  not shrink silently.
* `pty_pair`: two pseudo-terminals joined by socat (fails without socat).
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from .tools import PeerBinaries, PeerBuildError, build_peers, socat_pair


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
