"""Every public path the documentation shows imports, and every deprecated name or path
still works but warns, naming its new home (docs/DESIGN.md, "Public paths").

An old name resolves to the very object of its new name, so code written against it
keeps working until it moves; the warning says where to.
"""

from __future__ import annotations

import importlib
import re
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

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
    ("pyrtu.bridge.outbox", "Outbox"): ("pyrtu.outbox.outbox", "Outbox"),
    ("pyrtu.bridge.outbox", "OutboxError"): ("pyrtu.outbox.outbox", "OutboxError"),
    ("pyrtu.bridge.outbox", "OutboxFull"): ("pyrtu.outbox.outbox", "OutboxFull"),
    ("pyrtu.bridge.outbox", "OutboxLimits"): ("pyrtu.outbox.outbox", "OutboxLimits"),
    ("pyrtu.bridge.report", "Reporter"): ("pyrtu.outbox.report", "Reporter"),
    ("pyrtu.bridge.report", "Report"): ("pyrtu.outbox.report", "Report"),
    ("pyrtu.cli", "Command"): ("pyrtu.cli.app", "Subcommand"),
    ("pyrtu.cli.app", "Command"): ("pyrtu.cli.app", "Subcommand"),
}

ROOT = Path(__file__).resolve().parent.parent
#: the root re-export modules kept as documented paths, and their homes
KEPT_FACES = {
    "pyrtu.aio": "pyrtu.drivers.aio",
    "pyrtu.line": "pyrtu.core.line",
    "pyrtu.data": "pyrtu.pdu.data",
    "pyrtu.ascii": "pyrtu.core.ascii",
    "pyrtu.tcp_server": "pyrtu.tcp.server",
}
#: the deprecated root modules: each old name -> its new path (written out, not
#: computed from the code under test)
DEPRECATED_FACES: dict[str, dict[str, str]] = {
    "pyrtu.timing": {
        "Timing": "pyrtu.Timing",
        **{
            n: f"pyrtu.core.timing.{n}"
            for n in (
                "BYTESIZES", "MAX_BAUDRATE", "MIN_BAUDRATE", "MODES", "PARITIES", "STOPBITS",
                "TIMING_RULES", "apply_overrides", "bits_per_char", "check_baudrate",
                "check_bytesize", "check_mode", "check_parity", "check_stopbits",
                "check_timing", "compute_timing", "positive_seconds", "seconds_to_us",
            )
        },
    },
    "pyrtu.rules": {
        "BONFIGLIOLI": "pyrtu.BONFIGLIOLI",
        "CV100": "pyrtu.CV100",
        "LengthRule": "pyrtu.LengthRule",
        "RULE_COUNT": "pyrtu.core.rules.RULE_COUNT",
        "RULE_FIXED": "pyrtu.core.rules.RULE_FIXED",
        "RULE_NONE": "pyrtu.core.rules.RULE_NONE",
        "RuleTable": "pyrtu.core.rules.RuleTable",
        "check_rules": "pyrtu.core.rules.check_rules",
    },
    "pyrtu.functions": {
        n: f"pyrtu.pdu.functions.{n}"
        for n in (
            "DIAGNOSTICS", "ENCAPSULATED_INTERFACE", "FUNCTION_NAMES", "GET_COMM_EVENT_COUNTER",
            "GET_COMM_EVENT_LOG", "MASK_WRITE_REGISTER", "MEI_DEVICE_ID", "READ_COILS",
            "READ_DISCRETE_INPUTS", "READ_EXCEPTION_STATUS", "READ_FIFO_QUEUE",
            "READ_FILE_RECORD", "READ_HOLDING_REGISTERS", "READ_INPUT_REGISTERS",
            "READ_WRITE_REGISTERS", "REPORT_SERVER_ID", "WRITE_FILE_RECORD",
            "WRITE_MULTIPLE_COILS", "WRITE_MULTIPLE_REGISTERS", "WRITE_SINGLE_COIL",
            "WRITE_SINGLE_REGISTER", "function_name",
        )
    },
    "pyrtu.errors": {
        **{
            n: f"pyrtu.{n}"
            for n in (
                "EXCEPTION_NAMES", "BusFault", "ExceptionResponseError", "FrameError",
                "ModbusError", "NoResponseError", "PortError", "SlaveException",
            )
        },
        **{
            n: f"pyrtu.pdu.errors.{n}"
            for n in ("NO_DEVICE_ANSWERED", "PortBusyError", "PureBackendWarning", "exception_name")
        },
    },
}  # fmt: skip


def _resolve(path: str) -> Any:
    """The object a dotted path names: its longest importable module, then attributes."""
    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for attr in parts[k:]:
            obj = getattr(obj, attr)
        return obj
    raise ImportError(path)


def _documented_paths() -> dict[str, str]:
    """Every ``pyrtu.x.y`` and ``from pyrtu.x import y`` of README.md and docs/*.md ->
    where it is first shown."""
    found: dict[str, str] = {}
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for i, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
            where = f"{doc.name}:{i}"
            for m in re.finditer(r"(?<![\w/.])pyrtu(?:\.[A-Za-z_]\w*)+", line):
                found.setdefault(m.group(0), where)
            for m in re.finditer(r"from (pyrtu[\w.]*) import ([\w, ]+)", line):
                for name in m.group(2).split(","):
                    if name.split():
                        found.setdefault(f"{m.group(1)}.{name.split()[0]}", where)
    return found


def test_every_path_the_documents_show_imports_without_a_warning() -> None:
    """(docs/DESIGN.md may name the deprecated paths: its "Public paths" lists them.)"""
    paths = _documented_paths()
    assert len(paths) >= 50  # the documents were read
    old = {f"{m}.{n}" for m, n in DEPRECATED} | {f"{m}.{n}" for m in DEPRECATED_FACES for n in
                                                   DEPRECATED_FACES[m]}  # fmt: skip
    wrong = []
    for path, where in sorted(paths.items()):
        if where.startswith("DESIGN.md") and path in old:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                _resolve(path)
            except Exception as e:
                wrong.append(f"{where}: {path}: {type(e).__name__}: {e}")
    assert not wrong, wrong


@pytest.mark.parametrize(("face", "home"), sorted(KEPT_FACES.items()))
def test_a_kept_face_is_its_home_s_all(face: str, home: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        module = importlib.import_module(face)
        source = importlib.import_module(home)
        assert list(module.__all__) == list(source.__all__) and module.__all__
        for name in module.__all__:
            assert getattr(module, name) is getattr(source, name), name


@pytest.mark.parametrize("face", sorted(DEPRECATED_FACES))
def test_a_deprecated_face_warns_naming_the_new_path_of_each_name(face: str) -> None:
    module = importlib.import_module(face)
    assert sorted(module.__all__) == sorted(DEPRECATED_FACES[face])
    for name, new in DEPRECATED_FACES[face].items():
        with pytest.warns(DeprecationWarning) as caught:
            value = getattr(module, name)
        assert str(caught[0].message) == f"{face}.{name} is deprecated: use {new}"
        assert value is _resolve(new), name


def test_a_deprecated_face_still_serves_import_star_with_warnings() -> None:
    code = (
        "import warnings\n"
        "with warnings.catch_warnings(record=True) as w:\n"
        "    warnings.simplefilter('always')\n"
        "    from pyrtu.errors import *\n"
        "old = [x for x in w if 'is deprecated' in str(x.message)]\n"
        "print(PortBusyError.__module__, len(old))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["pyrtu.pdu.errors", "12"]


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
