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

from pyrtu.core.line import LineConfig
from pyrtu.protocol.client import ClientProtocol
from pyrtu.protocol.client_actions import Done, Send, Xfer, answer_pdu

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
    ("pyrtu.protocol", "Exchange"): ("pyrtu.protocol.client_actions", "Xfer"),
    ("pyrtu.protocol.client_actions", "Exchange"): ("pyrtu.protocol.client_actions", "Xfer"),
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


def _repeated_read() -> tuple[ClientProtocol, float]:
    """A client protocol on a timed RTU line that has learned a read's answer length
    (one answer taken), so that the same read again may go as one `Xfer`."""
    line = LineConfig(baudrate=19200)
    p = ClientProtocol(line, timeout=0.5)
    t = 100.0
    for _ in range(2):
        p.start(1, bytes.fromhex("0300000001"), answer_pdu, t)
        action = p.next_action(t)
        while not isinstance(action, Done):
            if isinstance(action, Send):
                end = t + 0.01
                p.transmitted(end, t)
                answer = bytes.fromhex("01030200 07")
                p.receive_data(answer + _crc(answer), end + 0.005)
                t = end + 0.005
            else:
                p.wait_done(b"", max(t, action.until))
                t = max(t, action.until)
            action = p.next_action(t)
        t += 0.1
    return p, t


def _crc(data: bytes) -> bytes:
    import pyrtu

    return pyrtu.crc16(data).to_bytes(2, "little")


def test_next_action_exchange_keyword_warns_and_still_plans_an_xfer() -> None:
    p, t = _repeated_read()
    p.start(1, bytes.fromhex("0300000001"), answer_pdu, t)
    with pytest.warns(
        DeprecationWarning,
        match=r"next_action\(exchange=...\) is deprecated: "
        r"use next_action\(xfer=...\)",
    ):
        old = p.next_action(t, exchange=True)
    assert isinstance(old, Xfer)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert p.next_action(t, xfer=True) == old


def test_exchanged_warns_and_reports_as_xfer_done() -> None:
    p, t = _repeated_read()
    p.start(1, bytes.fromhex("0300000001"), answer_pdu, t)
    plan = p.next_action(t, xfer=True)
    assert isinstance(plan, Xfer)
    answer = bytes.fromhex("0103020007")
    answer += _crc(answer)
    with pytest.warns(
        DeprecationWarning,
        match="ClientProtocol.exchanged is deprecated: use ClientProtocol.xfer_done",
    ):
        p.exchanged(t, t + 0.004, answer, len(answer), t + 0.01, t + 0.01)
    done = p.next_action(t + 0.01)
    assert isinstance(done, Done) and done.result() == bytes.fromhex("03020007")


def test_abandoned_exchange_warns_and_acts_as_abandoned_xfer() -> None:
    p, t = _repeated_read()
    with pytest.warns(
        DeprecationWarning,
        match="ClientProtocol.abandoned_exchange is deprecated: use ClientProtocol.abandoned_xfer",
    ):
        p.abandoned_exchange(t, 0.0, t + 0.001)
    assert p.late_answer_over_at() == pytest.approx(t + p.timeout)
