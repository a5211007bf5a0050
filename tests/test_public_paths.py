"""Every public path the documentation shows imports, and every deprecated name or path
still works but warns, naming its new home (docs/DESIGN.md, "Public paths").

An old name resolves to the very object of its new name, so code written against it
keeps working until it moves; the warning says where to.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings

import pytest

#: old (module, name) -> new (module, name): renamed or moved, kept as deprecated aliases
DEPRECATED: dict[tuple[str, str], tuple[str, str]] = {
    ("pyrtu.gateway.server", "TcpServer"): ("pyrtu.tcp.server", "TcpServer"),
    ("pyrtu.gateway.server", "Application"): ("pyrtu.tcp.server", "Application"),
    ("pyrtu.gateway.server", "LocalBus"): ("pyrtu.tcp.server", "LocalBus"),
    ("pyrtu.gateway.server", "UNIT_SELF"): ("pyrtu.tcp.server", "UNIT_SELF"),
    ("pyrtu.gateway.server", "UNIT_DIRECT"): ("pyrtu.tcp.server", "UNIT_DIRECT"),
    ("pyrtu.poller", "Request"): ("pyrtu.poller.schedule", "ScheduledRequest"),
    ("pyrtu.gateway", "Bus"): ("pyrtu.gateway.gateway", "GatewayBus"),
    ("pyrtu.gateway.gateway", "Bus"): ("pyrtu.gateway.gateway", "GatewayBus"),
    ("pyrtu.protocol", "State"): ("pyrtu.protocol.client_actions", "ClientState"),
    ("pyrtu.protocol.client", "State"): ("pyrtu.protocol.client_actions", "ClientState"),
}


@pytest.mark.parametrize(
    ("old", "new"), sorted(DEPRECATED.items()), ids=lambda k: ".".join(k) if k else ""
)
def test_a_deprecated_name_warns_naming_the_new_one(
    old: tuple[str, str], new: tuple[str, str]
) -> None:
    module = importlib.import_module(old[0])
    with pytest.warns(DeprecationWarning) as caught:
        value = getattr(module, old[1])
    message = str(caught[0].message)
    assert f"{old[0]}.{old[1]} is deprecated" in message
    assert f"use {new[0]}.{new[1]}" in message
    assert caught[0].filename == __file__  # reported at the user's line
    assert value is getattr(importlib.import_module(new[0]), new[1])


@pytest.mark.parametrize(("old", "new"), sorted(DEPRECATED.items()), ids=str)
def test_the_new_name_is_used_without_a_warning(old: tuple[str, str], new: tuple[str, str]) -> None:
    module = importlib.import_module(new[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        getattr(module, new[1])


def test_a_name_that_never_was_is_still_an_attribute_error() -> None:
    missing = "no_such_name"
    for module in {old[0] for old in DEPRECATED}:
        with pytest.raises(AttributeError, match=missing):
            getattr(importlib.import_module(module), missing)


def test_from_import_of_an_old_name_warns_in_a_fresh_interpreter() -> None:
    """``from pyrtu.gateway.server import TcpServer``, as a user wrote it, still works
    and warns (the first import of the module, nothing loaded before)."""
    code = (
        "import warnings; warnings.simplefilter('error')\n"
        "try:\n"
        "    from pyrtu.gateway.server import TcpServer\n"
        "except DeprecationWarning as w:\n"
        "    print(w)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "pyrtu.gateway.server.TcpServer is deprecated: use pyrtu.tcp.server.TcpServer" in (
        out.stdout
    )
