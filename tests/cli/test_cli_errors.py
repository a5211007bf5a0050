"""Bad command lines: a clear message naming the flag, exit 2 (usage) or 3 (port or
file), never a traceback; the bus directory lock; exclusive ports; captures."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import Background, pyrtu

from pyrtu import Master, Slave
from pyrtu.cli import main
from pyrtu.drivers.port import open_port
from pyrtu.pdu.errors import PortError
from pyrtu.protocol.datastore import DataStore
from pyrtu.vbus import BusDirectoryBusy, VirtualBus
from pyrtu.vbus.capture import RECORD

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))

import capsynth  # noqa: E402

NOPORT = "/nonexistent/ttyX"

# (command line, exit code, text the message must contain)
BAD: list[tuple[str, int, str]] = [
    # numbers out of range, nan, inf, negative, huge, not numbers
    (f"read {NOPORT} 0 --baudrate 0", 2, "--baudrate"),
    (f"read {NOPORT} 0 --baudrate -5", 2, "--baudrate"),
    (f"read {NOPORT} 0 --baudrate 100000000", 2, "--baudrate"),
    (f"read {NOPORT} 0 --baudrate nan", 2, "--baudrate"),
    (f"read {NOPORT} 0 --timeout nan", 2, "--timeout"),
    (f"read {NOPORT} 0 --timeout inf", 2, "--timeout"),
    (f"read {NOPORT} 0 --timeout -1", 2, "--timeout"),
    (f"read {NOPORT} 0 --retries -1", 2, "--retries"),
    (f"read {NOPORT} 0 --retries 1000000000", 2, "--retries"),
    (f"read {NOPORT} 0 --t35 1e30", 2, "--t35"),
    (f"read {NOPORT} 0 --t35 inf", 2, "--t35"),
    (f"read {NOPORT} -1", 2, "ADDRESS"),
    (f"read {NOPORT} 70000", 2, "ADDRESS"),
    (f"read {NOPORT} 0 --slave 300", 2, "--slave"),
    (f"read {NOPORT} 0 --order XYZW", 2, "--order"),
    (f"read {NOPORT} 0 0", 2, "COUNT"),
    (f"read {NOPORT} 0 126", 2, "COUNT 126"),
    (f"read {NOPORT} 0 2001 --table coils", 2, "COUNT 2001"),
    (f"read {NOPORT} 65535 10", 2, "ADDRESS 65535"),
    (f"poll {NOPORT} 65535 2", 2, "ADDRESS 65535"),
    (f"write {NOPORT} 65535 1 2", 2, "ADDRESS 65535"),
    (f"write {NOPORT} 0 --type string ''", 2, "VALUE"),
    (f"write {NOPORT} 0 --type float32 1e39", 2, "float32 range"),
    (f"write {NOPORT} 0 --type float32 abc", 2, "float32"),
    (f"write {NOPORT} 0 70000", 2, "uint16"),
    (f"read {NOPORT} 0 --type uint64 --order high", 2, "--order: order of a uint64"),
    (f"write {NOPORT} 0 --type int8 --order ABCDEFGH 128", 2, "-128..127"),
    (f"write {NOPORT} 0 --type bcd16 10000", 2, "bcd16 is 0..9999"),
    (f"write {NOPORT} 0 --type float16 70000", 2, "float16 range"),
    (f"write {NOPORT} 0x10000 1", 2, "ADDRESS"),
    (f"poll {NOPORT} 0 --rate nan", 2, "--rate"),
    (f"poll {NOPORT} 0 --rate inf", 2, "--rate"),
    (f"poll {NOPORT} 0 --rate -1", 2, "--rate"),
    (f"poll {NOPORT} 0 --count 0", 2, "--count"),
    (f"poll {NOPORT} 0 --interval 0", 2, "--interval"),
    (f"scan {NOPORT} --register -1", 2, "--register"),
    (f"scan {NOPORT} --range 0-300", 2, "--range"),
    (f"info {NOPORT} --object 300", 2, "--object"),
    ("sniff --example --count 0", 2, "--count"),
    ("sniff --example --count -1", 2, "--count"),
    ("sniff --example --duration -1", 2, "--duration"),
    ("sniff --example --baudrate 0", 2, "--baudrate"),
    (f"sniff {NOPORT} --capture x.cap", 2, "not both"),
    ("sniff", 2, "--capture"),
    (f"simulate cfw701 --port {NOPORT} --address 300", 2, "--address"),
    (f"simulate cfw701 --port {NOPORT} --baudrate 0", 2, "--baudrate"),
    ("vbus --drops 0", 2, "--drops"),
    ("vbus --drops 10000", 2, "--drops"),
    ("vbus --baud 0", 2, "--baud"),
    ("vbus --baud 100000000", 2, "--baud"),
    ("vbus --duration -1", 2, "--duration"),
    ("vbus --duration nan", 2, "--duration"),
    ("vbus --duration inf", 2, "--duration"),
    ("vbus --echo 5 --duration 0.1", 2, "--echo"),
    ("vbus --unplug 9:1 --duration 0.1", 2, "--unplug"),
    ("vbus --unplug 0:-5", 2, "--unplug"),
    ("vbus --bit-flip-rate nan", 2, "--bit-flip-rate"),
    ("vbus --drop-rate 2", 2, "--drop-rate"),
    ("vbus --gap nan", 2, "--gap"),
    ("vbus --batch -1", 2, "--batch"),
    ("vbus --batch-bytes 0", 2, "--batch-bytes"),
    ("demo --baudrate 0", 2, "--baudrate"),
    ("demo --baudrate 100000000", 2, "--baudrate"),
    ("demo --duration nan", 2, "--duration"),
    # ports and files
    (f"read {NOPORT} 0", 3, NOPORT),
    (f"sniff {NOPORT}", 3, NOPORT),
    ("sniff --capture /nonexistent/x.cap", 3, "/nonexistent/x.cap"),
    ("sniff --capture /", 3, "directory"),
    ("sniff --capture /dev/null", 3, "empty file"),
    (f"simulate cfw701 --port {NOPORT}", 3, NOPORT),
    ("vbus --dir /proc/pyrtu-x --duration 0.1", 3, "--dir /proc/pyrtu-x"),
    ("vbus --dir /etc/hostname --duration 0.1", 3, "--dir /etc/hostname: not a directory"),
    ("vbus --dir /proc --duration 0.1", 3, "--dir /proc: cannot create the lock file"),
    ("vbus --capture /proc/pyrtu-x/y.cap --duration 0.1", 3, "--capture /proc/pyrtu-x/y.cap"),
    ("vbus --capture / --duration 0.1", 3, "--capture /"),
]


def run_main(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``pyrtu ARGV`` in this process: an uncaught exception fails the test."""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(("line", "code", "needle"), BAD, ids=[b[0] for b in BAD])
def test_bad_command_lines(
    line: str, code: int, needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    got, _, err = run_main(shlex.split(line), capsys)
    assert got == code, err
    assert needle in err
    assert "Traceback" not in err


def test_no_traceback_in_a_real_process(tmp_path: Path) -> None:
    # The same as a user sees it: separate processes, stderr as printed.
    for line, code, needle in (BAD[0], BAD[-3], ("demo --baudrate -1", 2, "--baudrate")):
        r = pyrtu(*shlex.split(line))
        assert r.code == code and needle in r.err and "Traceback" not in r.err, r.err


def test_usage_errors_are_json_too(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run_main(["read", NOPORT, "0", "--baudrate", "0", "--json"], capsys)
    assert code == 2 and "--baudrate" in err
    doc = json.loads(out)
    assert doc["ok"] is False and doc["error"] == "usage" and doc["exit_code"] == 2
    assert "--baudrate" in doc["message"]
    code, out, _ = run_main(["sniff", "--capture", "/dev/null", "--json"], capsys)
    assert code == 3 and json.loads(out)["error"] == "port"
    code, out, _ = run_main(["read", NOPORT, "0", "--baudrate", "0"], capsys)
    assert code == 2 and out == ""  # without --json: nothing on stdout


def test_the_interrupted_message_says_it_once() -> None:
    from pyrtu.cli.common import report_error

    class Err:
        text = ""

        def write(self, s: str) -> None:
            Err.text += s

    saved = sys.stderr
    sys.stderr = Err()
    try:
        assert report_error("read", KeyboardInterrupt(), False) == 130
    finally:
        sys.stderr = saved
    assert Err.text.strip() == "pyrtu read: interrupted: stopped by SIGINT (Ctrl-C)"


def test_sniff_a_missing_port_does_not_say_listening() -> None:
    r = pyrtu("sniff", NOPORT)
    assert r.code == 3 and "listening on" not in r.err and NOPORT in r.err


# -- captures on the command line -------------------------------------------------------


def test_sniff_bad_captures_exit_3_with_clear_messages(tmp_path: Path) -> None:
    cases = {
        "empty.cap": (b"", "empty file"),
        "random.cap": (os.urandom(3000).replace(b"\n", b"."), "not a pyrtu capture"),
        "header.cap": (b"PYRTUCAP 1 baudrate=fast\n", "not a valid pyrtu capture"),
        "damaged.cap": (capsynth.header(2).line() + RECORD.pack(0, 9, 1) + b"\x01", "damaged"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        r = pyrtu("sniff", "--capture", path, "--json")
        assert r.code == 3, (name, r.err)
        assert message in r.err and str(path) in r.err, r.err
        assert "codec" not in r.err and "invalid literal" not in r.err
        doc = r.json_lines()[-1]
        assert doc["error"] == "port" and message in doc["message"]


def test_sniff_reports_a_cut_last_record(tmp_path: Path) -> None:
    path = tmp_path / "cut.cap"
    with open(path, "wb") as f:
        frames = capsynth.write_valid(f, 5000, registers=3)
    path.write_bytes(path.read_bytes()[:-3])  # the last frame loses 3 of its bytes
    r = pyrtu("sniff", "--capture", path, "--json")
    assert r.code == 0, r.err
    assert "warning" in r.err and "cut short" in r.err
    summary = r.json_lines()[-1]
    assert summary["frames"] == frames - 1
    assert any("cut short" in w for w in summary["warnings"])
    plain = pyrtu("sniff", "--capture", path)
    assert "cut short" in plain.err and f"{frames - 1} frames" in plain.out


def test_sniff_a_big_capture_streams(tmp_path: Path) -> None:
    path = tmp_path / "poll.cap"
    with open(path, "wb") as f:
        frames = capsynth.write_valid(f, 300_000, registers=20)
    r = pyrtu("sniff", "--capture", path, "--json", timeout=120)
    assert r.code == 0, r.err
    docs = r.json_lines()
    assert docs[-1]["frames"] == frames == len(docs) - 1
    assert docs[-1]["by_kind"] == {"request": frames // 2, "response": frames // 2}
    assert "warnings" not in docs[-1]


# -- one bus per directory -------------------------------------------------------------------


def test_a_second_bus_in_the_same_directory_is_refused(tmp_path: Path) -> None:
    d = tmp_path / "bus"
    with VirtualBus(2, parity="N", directory=str(d)) as first:
        link = os.readlink(first.paths[1])
        with pytest.raises(BusDirectoryBusy) as info:
            VirtualBus(2, parity="N", directory=str(d)).start()
        assert info.value.pid == os.getpid() and str(d) in str(info.value)
        assert os.readlink(first.paths[1]) == link  # untouched
        r = pyrtu("vbus", "--dir", d, "--duration", "0.2")
        assert r.code == 3, r.err
        assert str(d) in r.err and f"pid {os.getpid()}" in r.err and "Traceback" not in r.err
        assert os.readlink(first.paths[1]) == link
        assert os.path.exists(first.paths[0])
    assert not os.path.exists(d / ".pyrtu-vbus.lock")
    # a lock file left by a dead process is taken over
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    (d / ".pyrtu-vbus.lock").write_text(dead.stdout)
    with VirtualBus(1, parity="N", directory=str(d)) as again:
        assert (d / ".pyrtu-vbus.lock").read_text().strip() == str(os.getpid())
        assert os.path.islink(again.paths[0])


def test_the_cli_bus_holds_its_directory(tmp_path: Path) -> None:
    d = tmp_path / "clibus"
    bus = Background("vbus", "--dir", d, "--drops", "2", "--parity", "N", "--duration", "20")
    try:
        first = bus.line(timeout=15).strip()
        assert first == str(d / "drop0")
        link = os.readlink(first)
        r = pyrtu("vbus", "--dir", d, "--duration", "0.2")
        assert r.code == 3 and f"pid {bus.proc.pid}" in r.err and str(d) in r.err, r.err
        assert os.readlink(first) == link
    finally:
        bus.proc.terminate()
        done = bus.finish(timeout=15)
    assert done.code == 0, done.err


# -- exclusive ports ---------------------------------------------------------------------------


def test_ports_are_opened_exclusively_on_ptys(tmp_path: Path) -> None:
    with VirtualBus(3, parity="N") as bus:
        path = bus.paths[1]
        first = open_port(path, parity="N")
        try:
            with pytest.raises(PortError, match="busy") as info:
                open_port(path, parity="N")
            assert path in str(info.value) and "exclusive=False" in str(info.value)
            with pytest.raises(PortError, match="busy"):
                Master(path, parity="N")
            with pytest.raises(PortError, match="busy"):
                Slave(path, 1, DataStore(), parity="N")
            shared = Master(path, parity="N", exclusive=False)
            shared.close()
            slave = Slave(path, 1, DataStore(), parity="N", exclusive=False)
            slave.close()
            r = pyrtu("read", path, "0", "--parity", "N", "--json")
            assert r.code == 3 and "busy" in r.err and "--no-exclusive" in r.err, r.err
            assert r.json()["error"] == "port"
            # --no-exclusive shares the port: the read reaches the bus (no slave: exit 4)
            r = pyrtu("read", path, "0", "--parity", "N", "--no-exclusive", "--timeout", "0.05")
            assert r.code == 4, r.err
        finally:
            first.close()
        open_port(path, parity="N").close()  # free again


def test_a_second_simulator_on_a_drop_is_refused() -> None:
    with VirtualBus(2, parity="N") as bus:
        sim = Background(
            "simulate", "cfw701", "--port", bus.paths[1], "-P", "N", "-d", "20", "--json"
        )
        try:
            sim.line(timeout=15)  # ready
            second = pyrtu("simulate", "cfw701", "--port", bus.paths[1], "-P", "N", "-d", "1")
            assert second.code == 3, second.err
            assert "busy" in second.err and bus.paths[1] in second.err
            # the first still answers every request
            with Master(bus.paths[0], parity="N", timeout=1.0) as master:
                for _ in range(7):
                    assert len(master.read_holding_registers(1, 680, 1)) == 1
        finally:
            sim.proc.terminate()
            sim.finish(timeout=15)


# -- demo at slow and fast rates -------------------------------------------------------------


def test_demo_at_1200_baud() -> None:
    t = time.monotonic()
    r = pyrtu("demo", "--baudrate", "1200", "--plain", "--duration", "3", timeout=90)
    assert r.code == 0, r.err
    assert "0 errors" in r.out, r.out
    assert time.monotonic() - t < 90


def test_the_drop_cap_is_the_buses() -> None:
    from pyrtu.cli.vbus import MAX_DROPS as CLI_MAX
    from pyrtu.vbus import MAX_DROPS

    assert CLI_MAX == MAX_DROPS == 248
    with pytest.raises(ValueError, match=r"1\.\.248 drops"):
        VirtualBus(249)


def test_vbus_capture_is_not_written_over_unless_asked(tmp_path: Path) -> None:
    """An earlier capture is refused (exit 2, naming --capture) and left as it was;
    --overwrite replaces it; an empty file (mktemp's) holds nothing to lose (#27.14)."""
    cap = tmp_path / "bus.cap"
    first = pyrtu("vbus", "--drops", "2", "--capture", cap, "--duration", "0.2")
    assert first.code == 0, first.err
    before = cap.read_bytes()
    assert before  # the header at least

    again = pyrtu("vbus", "--drops", "2", "--capture", cap, "--duration", "0.2")
    assert again.code == 2, again.err
    assert f"--capture {cap}: the file exists ({len(before)} bytes)" in again.err
    assert "--overwrite" in again.err and "Traceback" not in again.err
    assert again.out == ""  # refused before any drop was made
    assert cap.read_bytes() == before

    replaced = pyrtu(
        "vbus",
        "--drops",
        "2",
        "--capture",
        cap,
        "--duration",
        "0.2",
        "--overwrite",
        "--baud",
        "9600",
    )
    assert replaced.code == 0, replaced.err
    assert cap.read_bytes() != before  # a new capture: a header of another line

    one = tmp_path / "one.cap"  # the boundary: one byte is something to lose
    one.write_bytes(b"x")
    refused = pyrtu("vbus", "--drops", "2", "--capture", one, "--duration", "0.2")
    assert refused.code == 2 and "(1 bytes)" in refused.err, refused.err
    assert one.read_bytes() == b"x"

    empty = tmp_path / "empty.cap"
    empty.touch()
    fresh = pyrtu("vbus", "--drops", "2", "--capture", empty, "--duration", "0.2")
    assert fresh.code == 0, fresh.err
    assert empty.stat().st_size > 0
