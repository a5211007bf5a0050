"""``pyrtu simulate`` unattended: a port that vanishes is reported once, reopened when
it returns while the other drives carry on; the exit status says whether a port was
still down at the end; two devices answering one address are warned about; ``--tcp``
alone names no serial format.  Real virtual buses, real ``python -m pyrtu``."""

from __future__ import annotations

import contextlib
import json
import signal
import time
from collections.abc import Callable
from typing import Any

import pytest
from cli_helpers import Background, pyrtu

from pyrtu import ExceptionResponseError, FrameError, Master, NoResponseError
from pyrtu.devices import weg
from pyrtu.vbus import VirtualBus

BAUD = 38400
SERIAL = ("--baudrate", str(BAUD), "--parity", "N")


def until(check: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.05)
    return check()


def next_json(bg: Background, kind: str, timeout: float = 15.0) -> dict[str, Any]:
    """The next ``--json`` line of type ``kind`` (the others are skipped)."""
    deadline = time.monotonic() + timeout
    while True:
        doc: dict[str, Any] = json.loads(bg.line(timeout=max(0.1, deadline - time.monotonic())))
        if doc.get("type") == kind:
            return doc


def reads(master: Master, slave: int, register: int = 680) -> bool:
    """Whether ``slave`` answered (no answer or a garbled one: False)."""
    try:
        return master.read_holding_registers(slave, register, 1) is not None
    except (NoResponseError, FrameError):
        return False


@pytest.mark.wall_clock
def test_an_unplugged_port_comes_back_and_the_other_drive_carries_on() -> None:
    """Two drives on two buses; the second bus's drop is unplugged: one "port_lost"
    line, the first drive answers all along, the second answers again after replug
    with its state kept (the drive started before the outage still runs); exit 0."""
    with (
        VirtualBus(2, baudrate=BAUD, parity="N") as a,
        VirtualBus(2, baudrate=BAUD, parity="N") as b,
    ):
        ports = [a.paths[1], b.paths[1]]
        bg = Background(
            "simulate", "cfw701", "-p", ports[0], "-p", ports[1], *SERIAL, "-a", 7,
            "--state", "stopped", "--json",
        )  # fmt: skip
        try:
            assert next_json(bg, "ready")["ports"] == ports
            with (
                Master(a.paths[0], BAUD, parity="N", timeout=0.5) as ma,
                Master(b.paths[0], BAUD, parity="N", timeout=0.5) as mb,
            ):
                weg.CFW701(mb, 7).start()
                assert weg.CFW701(mb, 7).status().running
                b.unplug(1)
                lost = next_json(bg, "port_lost")
                assert lost["port"] == ports[1] and lost["error"]
                for _ in range(10):  # the other drive answers throughout the outage
                    assert weg.CFW701(ma, 7).identify()["product_code"] == "CFW701"
                time.sleep(1.5)  # several retries (0.5 s, 1 s, ...) while it is away
                b.replug(1)
                back = next_json(bg, "port_back")
                assert back["port"] == ports[1] and back["attempts"] >= 1
                assert until(lambda: reads(mb, 7), timeout=10)
                assert weg.CFW701(mb, 7).status().running  # the same drive, its state kept
                assert not weg.CFW701(ma, 7).status().running
            bg.proc.send_signal(signal.SIGTERM)
            r = bg.finish()
        finally:
            bg.kill()
    assert r.code == 0, r.err
    docs = [json.loads(line) for line in r.out.splitlines() if line.strip()]
    assert [d["type"] for d in docs].count("port_lost") == 1  # reported once per outage
    assert r.err.count("port lost") == 1 and r.err.count("port back") == 1
    assert docs[-1]["type"] == "stopped" and docs[-1]["counters"]["requests"] >= 15


@pytest.mark.wall_clock
def test_a_port_still_down_at_the_end_exits_3_naming_it() -> None:
    with (
        VirtualBus(2, baudrate=BAUD, parity="N") as a,
        VirtualBus(2, baudrate=BAUD, parity="N") as b,
    ):
        ports = [a.paths[1], b.paths[1]]
        bg = Background("simulate", "acu", "-p", ports[0], "-p", ports[1], *SERIAL, "--json")
        try:
            next_json(bg, "ready")
            b.unplug(1)
            next_json(bg, "port_lost")
            with Master(a.paths[0], BAUD, parity="N", timeout=0.5) as ma:
                assert reads(ma, 1, 411)  # still served
            bg.proc.send_signal(signal.SIGTERM)
            r = bg.finish()
        finally:
            bg.kill()
    assert r.code == 3, r.err
    assert f"port error: {ports[1]}: still down at the end" in r.err
    assert r.json_lines()[-1]["error"] == "port"


@pytest.mark.wall_clock
def test_a_single_port_is_reopened_too() -> None:
    with VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        bg = Background(
            "simulate",
            "cv100",
            "-p",
            bus.paths[1],
            *SERIAL,
            "-a",
            5,
            "--state",
            "stopped",
            "--json",
        )
        try:
            next_json(bg, "ready")
            bus.unplug(1)
            next_json(bg, "port_lost")
            bus.replug(1)
            next_json(bg, "port_back")
            with Master(bus.paths[0], BAUD, parity="N", timeout=0.5) as m:
                assert until(lambda: reads(m, 5, 0x3300), timeout=10)
                assert m.read_holding_registers(5, 0x3300, 1) == [8]  # stopped, forward
            bg.proc.send_signal(signal.SIGTERM)
            r = bg.finish()
        finally:
            bg.kill()
    assert r.code == 0, r.err


@pytest.mark.wall_clock
@pytest.mark.parametrize("other", ["cfw701", "acu"])
def test_two_simulators_at_one_address_are_warned_about(other: str) -> None:
    """Same device: the answers collide (bytes come in while answering); a slower
    device (the ACU's response delay): the other's answer is heard whole."""
    with VirtualBus(3, baudrate=BAUD, parity="N") as bus:
        paths = bus.paths
        sims = [
            Background("simulate", dev, "-p", bus.paths[i + 1], *SERIAL, "-a", 7, "--json")
            for i, dev in enumerate(["cfw701", other])
        ]
        try:
            for bg in sims:
                next_json(bg, "ready")
            with Master(bus.paths[0], BAUD, parity="N", timeout=0.3) as m:
                for _ in range(5):
                    # garbled or not: the master asks; the ACU has no register 680, and
                    # when a loaded machine lets its exception answer come first, that
                    # is an answer too
                    with contextlib.suppress(ExceptionResponseError):
                        reads(m, 7)
            warnings = [next_json(bg, "warning", timeout=5) for bg in sims[1:]]
            for bg in sims:
                bg.proc.send_signal(signal.SIGTERM)
            results = [bg.finish() for bg in sims]
        finally:
            for bg in sims:
                bg.kill()
    assert warnings[0]["port"] == paths[2]
    assert "another device answers at address 7" in warnings[0]["message"]
    for r in results:
        assert r.code == 0
    assert "warning" in results[1].err


def test_one_simulator_alone_is_not_warned_about() -> None:
    """Reads, repeated writes (FC 06, whose answer repeats the request) and FC 16 to
    one simulator, another device on the bus: no warning."""
    with VirtualBus(3, baudrate=BAUD, parity="N") as bus:
        bg = Background("simulate", "cfw701", "-p", bus.paths[1], *SERIAL, "-a", 7, "--json")
        other = Background("simulate", "acu", "-p", bus.paths[2], *SERIAL, "-a", 3, "--json")
        try:
            next_json(bg, "ready")
            next_json(other, "ready")
            for t35 in (None, 0.0):  # a master that sends at once after each answer too
                with Master(bus.paths[0], BAUD, parity="N", timeout=1.0, t35=t35) as m:
                    for i in range(10):
                        assert m.read_holding_registers(7, 680, 2)
                        m.write_register(7, 683, 100 + i)  # FC 06 twice in a row: the
                        m.write_register(7, 683, 200 + i)  # answer is the request's echo
                        m.write_registers(7, 683, [300 + i])
                        assert m.read_holding_registers(3, 411, 1)
            for p in (bg, other):
                p.proc.send_signal(signal.SIGTERM)
            results = [bg.finish(), other.finish()]
        finally:
            bg.kill()
            other.kill()
    for r in results:
        assert r.code == 0 and "warning" not in r.err and '"warning"' not in r.out


def test_tcp_alone_names_no_serial_format() -> None:
    r = pyrtu("simulate", "cfw701", "--tcp", "127.0.0.1:0", "--duration", "0.3")
    assert r.code == 0, r.err
    first = r.err.splitlines()[0]
    assert "WEG CFW701 at address 1, Modbus TCP on 127.0.0.1:" in first
    assert "baud" not in first and "RTU" not in first
    js = pyrtu("simulate", "cfw701", "--tcp", "127.0.0.1:0", "--duration", "0.3", "--json")
    assert js.json_lines()[0]["format"] is None
