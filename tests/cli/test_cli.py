"""The ``pyrtu`` command line end to end: every command as a subprocess
(``python -m pyrtu ...``) against simulated drives and pyrtu slaves on a virtual
RS-485 bus, its error exits (missing port, refused parity, no response, exception
response, bad answer, usage) and its ``--json`` output."""

from __future__ import annotations

import math
import re
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from cli_helpers import Background, pyrtu

from pyrtu.devices import ACUSimulator, CFW701Simulator, CV100Simulator, weg
from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.protocol.datastore import DataStore
from pyrtu.vbus import VirtualBus

BAUD = 38400
CLI, SNIFFER, TESTER, SPARE = 0, 6, 7, 8  # drops
CFW, ACU, CV, GENERIC, GARBLED = 1, 3, 5, 10, 12  # slave addresses


@dataclass
class Bus:
    vbus: VirtualBus
    cfw701: CFW701Simulator
    acu: ACUSimulator
    cv100: CV100Simulator
    store: DataStore
    master: Master  # the test's own master, on drop TESTER
    capture: Path

    def path(self, drop: int) -> str:
        return self.vbus.paths[drop]

    @property
    def port(self) -> str:
        """The drop the command line's master uses."""
        return self.vbus.paths[CLI]


def _generic_store() -> DataStore:
    store = DataStore()
    store.holding_registers.add_range(0, [0] * 100)
    store.input_registers.add_range(0, [0] * 10, read_only=True)
    store.coils.add_range(0, [False] * 32)
    store.discrete_inputs.add_range(0, [False] * 16, read_only=True)
    return store


def _garbled(slave: Slave, unit: int, pdu: bytes) -> bytes:
    """FC 03 answered with two registers whatever was asked: a well-framed answer
    with the wrong data."""
    return b"\x03\x04\x00\x01\x00\x02"


@pytest.fixture(scope="module")
def bus(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bus]:
    capture = tmp_path_factory.mktemp("cli") / "bus.cap"
    sims = (CFW701Simulator(state="stopped"), ACUSimulator(), CV100Simulator(state="stopped"))
    store = _generic_store()
    with VirtualBus(9, baudrate=BAUD, parity="N", capture=str(capture)) as vbus:
        slaves: list[Slave] = []
        try:
            for drop, (sim, address) in enumerate(zip(sims, (CFW, ACU, CV), strict=True), 1):
                slaves.append(sim.serve(vbus.paths[drop], address, baudrate=BAUD, parity="N"))
            generic = Slave(
                vbus.paths[4],
                GENERIC,
                store,
                baudrate=BAUD,
                parity="N",
                identification={0: b"pyrtu", 1: b"TEST", 2: b"V0.1", 4: b"test slave"},
            )
            slaves.append(generic.start())
            garbled = Slave(vbus.paths[5], GARBLED, DataStore(), baudrate=BAUD, parity="N")
            garbled.register_function(3, _garbled)
            slaves.append(garbled.start())
            master = Master(vbus.paths[TESTER], BAUD, parity="N", timeout=1.0)
            yield Bus(vbus, *sims, store, master, capture)
            master.close()
        finally:
            for s in slaves:
                s.close()


#: the serial options for the virtual bus
SERIAL = ["--baudrate", str(BAUD), "--parity", "N"]


# -- help and usage ---------------------------------------------------------------------


def test_help_lists_every_command_and_the_exit_codes() -> None:
    r = pyrtu("--help")
    assert r.code == 0
    for name in ("read", "write", "poll", "scan", "info", "sniff", "simulate", "vbus", "demo"):
        assert f"\n    {name} " in r.out, name
    for code, kind in ((3, "port"), (4, "no_response"), (5, "exception"), (6, "frame")):
        assert f"{code}  {kind}" in r.out


def test_the_installed_script() -> None:
    script = Path(sys.executable).parent / "pyrtu"
    if not script.exists():
        pytest.skip("pyrtu is not installed as a script next to this interpreter")
    r = subprocess.run([script, "--version"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 0 and r.stdout.startswith("pyrtu ")


def test_no_command_and_bad_arguments_are_usage_errors(bus: Bus) -> None:
    assert pyrtu().code == 2
    r = pyrtu("read", bus.port, "--table", "nowhere", "0")
    assert r.code == 2 and "table is holding, input, coils or discrete" in r.err
    r = pyrtu("read", bus.port, *SERIAL, "--slave", "0", "0")
    assert r.code == 2 and "broadcast" in r.err


# -- read -----------------------------------------------------------------------------------


def test_read_for_people_with_a_profile(bus: Bus) -> None:
    r = pyrtu("read", bus.port, *SERIAL, "--slave", CFW, "680", "2", "--profile", "cfw701")
    assert r.code == 0, r.err
    status = bus.cfw701.get(weg.P_STATUS)
    assert f"[680] {status} (0x{status:04X})" in r.out
    assert "P680 status: stopped, forward, local" in r.out
    assert "[681] 0 (0x0000)" in r.out
    assert "TX" not in r.err
    verbose = pyrtu("-vv", "read", bus.port, *SERIAL, "--slave", CFW, "680")
    assert verbose.code == 0
    assert re.search(r"pyrtu.drivers.master: TX slave 1 fc 3: 01 03 02 a8 00 01", verbose.err)
    assert re.search(r"pyrtu.drivers.master: RX slave 1 fc 3: 01 03 02 ", verbose.err)


@pytest.mark.parametrize(
    ("kind", "order", "values", "registers"),
    [
        ("uint16", "ABCD", ["65535", "0x1234"], [0xFFFF, 0x1234]),
        ("int16", "ABCD", ["-2", "300"], [0xFFFE, 300]),
        ("int32", "CDAB", ["-100000"], [0x7960, 0xFFFE]),
        ("uint32", "DCBA", ["305419896"], [0x7856, 0x3412]),
        ("float32", "CDAB", ["1.5", "-2.25"], [0, 0x3FC0, 0, 0xC010]),
        ("float32", "BADC", ["3.14"], list(struct.unpack("<HH", struct.pack(">f", 3.14)))),
        # the types of issue 29, registers from struct (or by hand)
        ("int64", "CDAB", ["-2"], list(struct.unpack(">4H", struct.pack(">q", -2)))[::-1]),
        ("uint64", "ABCDEFGH", ["18446744073709551615"], [0xFFFF] * 4),
        ("float64", "DCBA", ["0.1"], list(struct.unpack("<4H", struct.pack(">d", 0.1)))[::-1]),
        ("float16", "ABCD", ["-2.5", "0.1"], [*struct.unpack(">H", struct.pack(">e", -2.5)),
                                             *struct.unpack(">H", struct.pack(">e", 0.1))]),
        ("bcd16", "ABCD", ["1234"], [0x1234]),
        ("bcd32", "CDAB", ["12345678"], [0x5678, 0x1234]),
        ("int8", "low", ["-2", "5"], [0x00FE, 0x0005]),
        ("uint8", "high", ["255"], [0xFF00]),
    ],
)  # fmt: skip
def test_write_then_read_typed_values(
    bus: Bus, kind: str, order: str, values: list[str], registers: list[int]
) -> None:
    common = [bus.port, *SERIAL, "--slave", GENERIC, "--type", kind, "--order", order]
    w = pyrtu("write", *common, "20", *values, "--json")
    assert w.code == 0, w.err
    doc = w.json()
    assert doc["registers"] == registers
    assert doc["function"] == (6 if len(registers) == 1 else 16)
    assert bus.store.holding_registers.get_many(20, len(registers)) == registers
    r = pyrtu("read", *common, "20", len(values), "--json")
    assert r.code == 0, r.err
    got = r.json()
    assert got["registers"] == registers and got["type"] == kind and got["order"] == order
    for text, value in zip(values, got["values"], strict=True):
        want = float(text) if kind.startswith("float") else int(text, 0)
        if not kind.startswith("float") or kind == "float16":
            assert value == want  # a float16 as its shortest decimal: 0.1
        else:
            assert math.isclose(value, want, rel_tol=1e-6)
    assert got["addresses"] == [
        20 + i * (len(registers) // len(values)) for i in range(len(values))
    ]


def test_strings(bus: Bus) -> None:
    common = [bus.port, *SERIAL, "--slave", GENERIC, "--type", "string"]
    assert pyrtu("write", *common, "40", "CFW701 drive").code == 0
    assert bus.store.holding_registers.get(40) == ord("C") << 8 | ord("F")
    r = pyrtu("read", *common, "40", "6")
    assert r.code == 0 and "[40] 'CFW701 drive'" in r.out
    swapped = pyrtu("read", *common, "--order", "BADC", "40", "3", "--json").json()
    assert swapped["values"] == ["FC7W10"]  # "CF" "W7" "01", bytes swapped
    one = [bus.port, *SERIAL, "--slave", GENERIC, "--type", "string1"]
    assert pyrtu("write", *one, "60", "ok").code == 0
    assert bus.store.holding_registers.get_many(60, 2) == [ord("o"), ord("k")]
    r = pyrtu("read", *one, "60", "3", "--json")  # 3 registers: the NUL after "ok" ends it
    assert r.code == 0 and r.json()["values"] == ["ok"], r.err


def test_coils_and_bits(bus: Bus) -> None:
    common = [bus.port, *SERIAL, "--slave", GENERIC, "--table", "coils"]
    w = pyrtu("write", *common, "3", "1", "off", "on", "--json")
    assert w.code == 0 and w.json()["function"] == 15
    assert [bus.store.coils.get(a) for a in (3, 4, 5)] == [True, False, True]
    single = pyrtu("write", *common, "4", "true")
    assert single.code == 0 and "(write_coil, FC 5)" in single.out
    r = pyrtu("read", *common, "2", "5", "--json")
    assert r.json()["values"] == [False, True, True, True, False]
    bus.store.discrete_inputs.set(7, True)
    bus.store.input_registers.set(2, 0xBEEF)
    d = pyrtu("read", bus.port, *SERIAL, "--slave", GENERIC, "--table", "discrete", "6", "3")
    assert d.code == 0 and d.out.split() == ["[6]", "0", "[7]", "1", "[8]", "0"]
    i = pyrtu("read", bus.port, *SERIAL, "--slave", GENERIC, "--table", "input", "2", "--json")
    assert i.json()["values"] == [0xBEEF]


def test_write_forced_functions(bus: Bus) -> None:
    common = [bus.port, *SERIAL, "--slave", GENERIC]
    r = pyrtu("write", *common, "--function", "16", "60", "7", "--json").json()
    assert (r["function"], r["transactions"]) == (16, 1)
    r = pyrtu("write", *common, "--function", "6", "61", "8", "9", "--json").json()
    assert (r["function"], r["transactions"]) == (6, 2)
    assert bus.store.holding_registers.get_many(60, 3) == [7, 8, 9]
    bad = pyrtu("write", *common, "--function", "5", "60", "1")
    assert bad.code == 2 and "does not write holding registers" in bad.err


def test_write_usage_errors(bus: Bus) -> None:
    common = [bus.port, *SERIAL, "--slave", GENERIC]
    r = pyrtu("write", *common, "--table", "input", "0", "1")
    assert r.code == 2 and "read-only" in r.err
    r = pyrtu("write", *common, "0", "-1", "--json")
    assert r.code == 2 and "--type int16" in r.err
    assert r.json() == {
        "ok": False,
        "error": "usage",
        "exit_code": 2,
        "message": r.json()["message"],
    }
    r = pyrtu("write", *common, "--table", "coils", "0", "maybe")
    assert r.code == 2 and "a bit is" in r.err


def test_write_drives_a_simulated_drive(bus: Bus) -> None:
    ref = weg.hz_to_13bit(12, 60)
    assert pyrtu("write", bus.port, *SERIAL, "--slave", CFW, "683", ref).code == 0
    assert bus.cfw701.get(weg.P_REFERENCE) == ref
    # P680 is read-only on the drive: exception 3 (the manual's case)
    r = pyrtu("write", bus.port, *SERIAL, "--slave", CFW, "680", "1", "--json")
    assert r.code == 5 and r.json()["exception_code"] == 3


# -- error exits ------------------------------------------------------------------------------


def test_missing_port(tmp_path: Path) -> None:
    r = pyrtu("read", tmp_path / "no-such-tty", "--slave", "1", "0", "--json")
    assert r.code == 3
    assert "port error" in r.err and "no-such-tty" in r.err
    assert r.json()["error"] == "port"


def test_refused_parity_on_a_pseudo_terminal(bus: Bus) -> None:
    r = pyrtu("read", bus.port, "--parity", "E", "--slave", CFW, "0")
    assert r.code == 3, r.err
    assert "parity" in r.err and "8E1" in r.err


@pytest.mark.wall_clock
def test_no_response(bus: Bus) -> None:
    t0 = time.monotonic()
    r = pyrtu("read", bus.port, *SERIAL, "--slave", "99", "0", "--timeout", "200ms", "--json")
    assert r.code == 4
    assert "no response" in r.err
    assert r.json()["error"] == "no_response"
    # A process start (imports: ~1 s on a loaded 2-core VM) and one 200 ms timeout:
    # 50 timeouts (10 s) only catch a CLI that waits for a default timeout or retries.
    assert time.monotonic() - t0 < 50 * 0.2


def test_exception_response(bus: Bus) -> None:
    r = pyrtu("read", bus.port, *SERIAL, "--slave", CFW, "9999", "--json")
    assert r.code == 5
    doc = r.json()
    assert (doc["error"], doc["slave"], doc["function"]) == ("exception", CFW, 3)
    assert (doc["exception_code"], doc["exception_name"]) == (2, "ILLEGAL DATA ADDRESS")
    people = pyrtu("read", bus.port, *SERIAL, "--slave", CFW, "9999")
    assert people.code == 5 and "exception 2 (ILLEGAL DATA ADDRESS)" in people.err


def test_bad_answer_is_a_frame_error(bus: Bus) -> None:
    r = pyrtu("read", bus.port, *SERIAL, "--slave", GARBLED, "0", "--timeout", "0.3", "--json")
    assert r.code == 6, r.err
    assert r.json()["error"] == "frame"


# -- poll ---------------------------------------------------------------------------------------


def test_poll_json_reports(bus: Bus) -> None:
    bus.store.holding_registers.set(0, 1234)
    r = pyrtu(
        "poll",
        bus.port,
        *SERIAL,
        *f"--slave {GENERIC} 0 2 --count 25 --rate 50 --interval 0.2 --json".split(),
    )
    assert r.code == 0, r.err
    docs = r.json_lines()
    assert docs[-1]["final"] is True and all(d["final"] is False for d in docs[:-1])
    assert len(docs) >= 2  # periodic reports, then the final one
    total = docs[-1]["total"]
    assert (total["transactions"], total["ok"], total["errors"]) == (25, 25, {})
    assert 10 < total["per_second"] <= 60
    lat = total["latency_ms"]
    assert 0 < lat["p50"] <= lat["p99"] <= lat["max"] < 1000
    assert docs[-1]["values"] == [1234, 0] and docs[-1]["addresses"] == [0, 1]


def test_poll_counts_errors_by_kind(bus: Bus) -> None:
    r = pyrtu(
        "poll",
        bus.port,
        *SERIAL,
        *"--slave 99 0 --count 3 --timeout 0.1 --rate 0 --json".split(),
    )
    assert r.code == 4
    final = r.json_lines()[-1]
    assert final["total"]["errors"] == {"no_response": 3}
    assert final["total"]["latency_ms"]["p50"] is None
    r = pyrtu("poll", bus.port, *SERIAL, "--slave", CFW, "9999", "--count", "2", "--rate", "0")
    assert r.code == 5
    assert "errors: exception_2 2" in r.out


@pytest.mark.wall_clock
def test_poll_for_people_until_the_duration(bus: Bus) -> None:
    t0 = time.monotonic()
    r = pyrtu(
        "poll",
        bus.port,
        *SERIAL,
        *f"--slave {CFW} 680 2 --profile cfw701 --duration 1.6 --interval 0.5".split(),
    )
    assert r.code == 0, r.err
    # It stops at the duration (1.6 s); the process start (~1 s on a loaded 2-core
    # VM) and the last transaction fit many times in 9 durations (14.4 s).
    assert time.monotonic() - t0 < 9 * 1.6
    lines = r.out.splitlines()
    assert len(lines) >= 3
    assert "tx/s" in lines[0] and "p50" in lines[0] and "[680]" in lines[0]
    assert "transactions in" in lines[-1] and "errors: none" in lines[-1]


# -- scan -----------------------------------------------------------------------------------------


def test_scan_finds_every_slave(bus: Bus) -> None:
    r = pyrtu("scan", bus.port, *SERIAL, "--range", "1-13", "--timeout", "0.1", "--json")
    assert r.code == 0, r.err
    doc = r.json()
    assert doc["slaves"] == [CFW, ACU, CV, GENERIC, GARBLED]
    answers = {e["slave"]: e["answer"] for e in doc["found"]}
    assert answers[CFW] == "response" and answers[GARBLED] == "garbled"
    assert answers[ACU] == "exception"  # a Vectron has no parameter 0: it is there all the same


def test_scan_with_identification_and_nothing_found(bus: Bus) -> None:
    r = pyrtu("scan", bus.port, *SERIAL, "--range", "1-3", "--identify")
    assert r.code == 0, r.err
    assert "WEG CFW701" in r.out and "2 slaves found (1, 3)" in r.out
    none = pyrtu("scan", bus.port, *SERIAL, "--range", "20-22", "--timeout", "0.05")
    assert none.code == 4 and "0 slaves found" in none.out


# -- info ----------------------------------------------------------------------------------------


def test_info(bus: Bus) -> None:
    r = pyrtu("info", bus.port, *SERIAL, "--slave", CFW)
    assert r.code == 0, r.err
    assert "VendorName (0x00):" in r.out and "WEG" in r.out and "CFW701" in r.out
    doc = pyrtu("info", bus.port, *SERIAL, "--slave", GENERIC, "--level", "regular", "--json")
    assert doc.code == 0, doc.err
    assert doc.json()["identification"]["ProductName"] == "test slave"
    one = pyrtu("info", bus.port, *SERIAL, "--slave", GENERIC, "--object", "1", "--json")
    assert one.json()["objects"] == [{"id": 1, "name": "ProductCode", "value": "TEST"}]


def test_info_without_fc43_and_with_a_profile(bus: Bus) -> None:
    r = pyrtu("info", bus.port, *SERIAL, "--slave", ACU)
    assert r.code == 5 and "--profile" in r.err
    p = pyrtu("info", bus.port, *SERIAL, "--slave", ACU, "--profile", "acu", "--json")
    assert p.code == 0, p.err
    assert p.json()["identification"]["model"] == "ACU"
    cv = pyrtu("info", bus.port, *SERIAL, "--slave", CV, "--profile", "cv100")
    assert cv.code == 0 and "software_version" in cv.out


# -- sniff --------------------------------------------------------------------------------------


def test_sniff_a_live_port_device_aware(bus: Bus) -> None:
    bg = Background(
        "sniff",
        bus.path(SNIFFER),
        *SERIAL,
        *"--profile cfw701 --count 4 --duration 10 --json".split(),
    )
    try:
        assert bus.vbus.wait_clients(SNIFFER, timeout=5)
        time.sleep(0.3)
        bus.master.read_holding_registers(CFW, weg.P_STATUS, 2)
        bus.master.write_register(CFW, weg.P_CONTROL, 0)
        r = bg.finish()
    finally:
        bg.kill()
    assert r.code == 0, r.err
    docs = r.json_lines()
    frames = [d for d in docs if d["type"] == "frame"]
    assert [f["kind"] for f in frames] == ["request", "response", "request", "response"]
    assert frames[0]["fields"] == {"address": 680, "count": 2}
    assert any(n.startswith("P680 status: ") for n in frames[1]["notes"])
    assert frames[3]["notes"] == ["P682 control: none"]
    assert docs[-1] == {
        "type": "summary",
        "frames": 4,
        "by_kind": {"request": 2, "response": 2},
        "discarded_bytes": 0,
    }


def test_sniff_a_capture_file(bus: Bus) -> None:
    bus.master.read_holding_registers(ACU, 411, 1)
    time.sleep(0.2)
    r = pyrtu("sniff", "--capture", bus.capture, "--profile", "acu")
    assert r.code == 0, r.err
    assert "411 status: " in r.out
    assert "REQUEST" in r.out and "RESPONSE" in r.out
    doc = pyrtu("sniff", "--capture", bus.capture, "--json").json_lines()
    assert doc[-1]["type"] == "summary" and doc[-1]["frames"] == len(doc) - 1 > 4


def test_sniff_the_sample_and_its_errors(tmp_path: Path) -> None:
    r = pyrtu("sniff", "--example")
    assert r.code == 0
    assert "DISCARD   3 bytes discarded (crc): 00 ff 13" in r.out
    assert "exception 2 (ILLEGAL DATA ADDRESS)" in r.out
    assert "read_parameter_32" in r.out
    assert "11 frames" in r.out
    missing = pyrtu("sniff", "--capture", tmp_path / "none.cap", "--json")
    assert missing.code == 3 and missing.json()["error"] == "port"
    assert pyrtu("sniff").code == 2


# -- simulate -----------------------------------------------------------------------------------


def sigterm_stopped(bg: Background) -> dict[str, Any]:
    """SIGTERM to ``pyrtu simulate --json``: it exits 0 and its last line is "stopped"."""
    bg.proc.send_signal(signal.SIGTERM)
    r = bg.finish()
    assert r.code == 0, r.err
    stopped: dict[str, Any] = r.json_lines()[-1]
    assert stopped["type"] == "stopped"
    return stopped


def test_simulate_serves_a_drive_until_sigterm(bus: Bus) -> None:
    bg = Background("simulate", "cfw701", "--port", bus.path(SPARE), *SERIAL, "-a", 7, "--json")
    try:
        ready = bg.line(timeout=10)
        assert '"type": "ready"' in ready and '"address": 7' in ready
        drive = weg.CFW701(bus.master, 7)
        assert drive.identify()["product_code"] == "CFW701"
        drive.start()
        assert drive.status().running
        stopped = sigterm_stopped(bg)
    finally:
        bg.kill()
    assert stopped["counters"]["requests"] >= 3


def test_simulate_for_a_duration_and_its_errors(bus: Bus, tmp_path: Path) -> None:
    bg = Background(
        "simulate", "acu", "--port", bus.path(SPARE), *SERIAL, "--duration", "1.5", "--watch"
    )
    try:
        assert "starting lockout" in bg.line(timeout=10)
        r = bg.finish()
    finally:
        bg.kill()
    assert r.code == 0 and "Bonfiglioli Vectron ACU at address 1" in r.err
    assert "stopped after" in r.err
    assert pyrtu("simulate", "cfw100", "--port", tmp_path / "nope", "-P", "N").code == 3
    refused = pyrtu("simulate", "cv100", "--port", bus.path(SPARE), "--parity", "E")
    assert refused.code == 3 and "parity" in refused.err
    assert pyrtu("simulate", "cfw999", "--port", bus.path(SPARE)).code == 2
    assert pyrtu("simulate", "acu", "--state", "stopped", "--port", bus.path(SPARE)).code == 2


def test_simulate_one_drive_per_port_in_one_process() -> None:
    """``--port`` twice: two drives, each with its own state, one per bus, served by
    one process; a bus still gone at the end makes it exit with a port error naming it."""
    with (
        VirtualBus(2, baudrate=BAUD, parity="N") as a,
        VirtualBus(2, baudrate=BAUD, parity="N") as b,
    ):
        ports = [a.paths[1], b.paths[1]]
        args = ["simulate", "cfw701", "-p", ports[0], "--port", ports[1], *SERIAL]
        bg = Background(*args, "-a", 7, "--state", "stopped", "--json")
        try:
            ready = bg.line(timeout=10)
            assert '"type": "ready"' in ready and f'"ports": ["{ports[0]}", "{ports[1]}"]' in ready
            with (
                Master(a.paths[0], BAUD, parity="N", timeout=1.0) as ma,
                Master(b.paths[0], BAUD, parity="N", timeout=1.0) as mb,
            ):
                on_a, on_b = weg.CFW701(ma, 7), weg.CFW701(mb, 7)
                assert on_a.identify()["product_code"] == "CFW701"
                assert on_b.identify()["product_code"] == "CFW701"
                on_a.start()
                assert on_a.status().running
                assert not on_b.status().running  # its own drive, still stopped
            stopped = sigterm_stopped(bg)
        finally:
            bg.kill()
        assert stopped["counters"]["requests"] >= 5

        bg = Background(*args, "-a", 7, "--json")
        try:
            assert '"type": "ready"' in bg.line(timeout=10)
            b.unplug(1)  # reported once and retried (tests/cli/test_simulate_ports.py) ...
            assert '"type": "port_lost"' in bg.line(timeout=10)
            bg.proc.send_signal(signal.SIGTERM)
            r = bg.finish()
        finally:
            bg.kill()
        assert r.code == 3 and ports[1] in r.err, r.err  # ... and still down at the end
    duplicate = pyrtu("simulate", "cv100", "-p", ports[0], "-p", ports[0], *SERIAL)
    assert duplicate.code == 2 and "--port" in duplicate.err
    tcp = pyrtu("simulate", "cv100", "-p", ports[0], "-p", ports[1], "--tcp", "127.0.0.1:0")
    assert tcp.code == 2 and "--tcp" in tcp.err


# -- ASCII -------------------------------------------------------------------------------------


def test_ascii_mode_read_and_sniff(bus: Bus) -> None:
    sim = CV100Simulator(state="stopped", mode="ascii")
    sim.serve(bus.path(SPARE), 6, baudrate=BAUD, parity="N")
    bg = Background(
        "sniff",
        bus.path(SNIFFER),
        *SERIAL,
        *"--mode ascii --profile cv100 --count 2 --duration 10 --json".split(),
    )
    try:
        assert bus.vbus.wait_clients(SNIFFER, timeout=5)
        time.sleep(0.3)
        r = pyrtu(
            "read",
            bus.port,
            *SERIAL,
            "--mode",
            "ascii",
            "--slave",
            "6",
            "0x3300",
            "--profile",
            "cv100",
        )
        assert r.code == 0, r.err
        assert (
            r.out.startswith("[0x3300] 8 (0x0008)") and "status word 1: stopped, forward" in r.out
        )
        sniffed = bg.finish()
    finally:
        bg.kill()
        sim.close()
    frames = sniffed.json_lines()[:2]
    assert [f["kind"] for f in frames] == ["request", "response"]
    assert frames[1]["notes"] == ["status word 1: stopped, forward"]
    no_ascii = pyrtu("read", bus.port, *SERIAL, "--slave", "6", "0x3300", "--timeout", "0.2")
    assert no_ascii.code == 4  # an ASCII drive does not answer RTU


# -- vbus ---------------------------------------------------------------------------------------


def test_vbus_runs_for_a_duration(tmp_path: Path) -> None:
    r = pyrtu("vbus", "--drops", "2", "--baudrate", "9600", "--dir", tmp_path, "--duration", "0.3")
    assert r.code == 0
    assert r.out.split() == [str(tmp_path / "drop0"), str(tmp_path / "drop1")]
    assert "9600 baud" in r.err
