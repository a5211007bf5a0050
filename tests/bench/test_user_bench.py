"""``pyrtu bench`` (#32.5): the suite's report, the line check of a device on a real
line (the virtual bus: pseudo-terminals, wire timing, and an adapter that holds
bytes back), over TCP, the HTML report, and bad input.

No figure's size is asserted (measurements, not tests); what is checked is what the
figures must be by construction: a round trip is at least the frames' time on the
wire (Serial Line 2.5.1: 10 bits a character in 8N1) plus the device's configured
response delay, the recommendation follows from the round trips as the text says."""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from cli_helpers import ROOT, env

import pyrtu
from pyrtu.bench.line import char_time, check_serial, check_tcp
from pyrtu.bench.timer import percentile, time_call

vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 19200
CHAR = 10 / BAUD  # 8N1: start, 8 data, stop


def pyrtu_bench(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pyrtu", "bench", *args],
        capture_output=True,
        text=True,
        env=env(),
        cwd=ROOT,
        timeout=timeout,
    )


@contextmanager
def device(delay: float = 0.0, faults: object = None) -> Iterator[str]:
    """A pyrtu slave at 7 on a two-drop virtual bus, holding registers 0..9 = 100..109
    and answering ``delay`` seconds after its t3.5; yields the master's drop."""
    with vbus.VirtualBus(2, baudrate=BAUD, parity="N", faults=faults) as bus:
        store = pyrtu.DataStore()
        store.holding_registers.add_range(0, list(range(100, 110)))
        with pyrtu.Slave(
            bus.paths[1], 7, store, baudrate=BAUD, parity="N", response_delay=delay
        ) as slave:
            slave.start()
            yield bus.paths[0]


# -- the pieces --------------------------------------------------------------------------


def test_percentile_is_the_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]  # 1..100
    assert percentile(values, 0.5) == 50.0
    assert percentile(values, 0.99) == 99.0
    assert percentile(values, 1.0) == 100.0
    assert percentile(values, 0.0) == 1.0
    assert percentile([3.0], 0.99) == 3.0
    with pytest.raises(ValueError, match="no values"):
        percentile([], 0.5)
    with pytest.raises(ValueError, match="q must be within"):
        percentile([1.0], 1.5)


def test_time_call_runs_for_its_budget_and_refuses_none() -> None:
    calls = []
    t = time_call(lambda: calls.append(1), 0.05)
    assert t.batches >= 5 and len(calls) >= t.batches * t.per_batch
    assert t.low <= t.median <= t.high
    with pytest.raises(ValueError, match="budget"):
        time_call(lambda: None, 0)


def test_character_time_is_the_spec_s() -> None:
    # Serial Line 2.5.1: 11 bits with parity (8E1) or two stop bits (8N2), 10 in 8N1
    assert char_time(9600, "E", 1, 8) == pytest.approx(11 / 9600)
    assert char_time(9600, "N", 2, 8) == pytest.approx(11 / 9600)
    assert char_time(9600, "N", 1, 8) == pytest.approx(10 / 9600)


# -- the line check on a real line ---------------------------------------------------------


def test_the_line_check_measures_what_the_wire_and_the_device_take() -> None:
    delay = 0.010
    with device(delay) as port:
        r = check_serial(
            port, 7, baudrate=BAUD, parity="N", stopbits=1, bytesize=8, count=3, samples=30
        )
    f = r.figures()
    assert f["transactions"] == 30 and f["failures"] == 0
    request, answer = 8 * CHAR, (5 + 2 * 3) * CHAR  # FC 03 of 3 registers
    assert f["request_wire"] == pytest.approx(request)
    assert f["answer_wire"] == pytest.approx(answer)
    t35 = 3.5 * CHAR
    # the slave answers t3.5 + its delay after the request's end: at least that
    assert f["answer_start_min"] >= t35 + delay - 1e-4
    assert min(r.round_trips) >= request + t35 + delay + answer - 1e-4
    assert f["round_trip_p50"] <= f["round_trip_p99"] <= f["round_trip_max"]
    # the virtual bus forwards bytes at the character rate: no batching, t3.5 observable
    assert f["batches"] is False
    assert (
        "t3.5" in f["recommended_framing"] and "strict=True may be used" in f["recommended_framing"]
    )
    expected = math.ceil(max(1.5 * f["round_trip_max"], 2 * f["round_trip_p99"]) * 100 - 1e-9) / 100
    assert f["recommended_timeout"] == pytest.approx(expected)


def test_an_adapter_that_holds_bytes_is_found_out() -> None:
    """FTDI-style delivery (the bus releases received bytes in bursts 16 ms after the
    first): answers come in one read, and lenient framing is recommended."""
    with device(0.0, vbus.Faults(batch_s=0.016)) as port:
        r = check_serial(
            port, 7, baudrate=BAUD, parity="N", stopbits=1, bytesize=8, count=10, samples=20
        )
    f = r.figures()
    assert f["transactions"] == 20
    assert f["batches"] is True
    assert f["reads_per_answer_p50"] == 1
    assert f["batching_p50"] > 0
    assert f["recommended_framing"].startswith("lenient")


def test_an_exception_answer_is_a_failure_that_says_so() -> None:
    with device() as port:
        r = check_serial(
            port, 7, baudrate=BAUD, parity="N", stopbits=1, bytesize=8, address=500, samples=3
        )
    assert r.round_trips == [] and len(r.failures) == 3
    assert "exception 2" in r.failures[0]


def test_a_silent_slave_is_a_failure_within_the_timeout() -> None:
    with device() as port:
        r = check_serial(
            port, 9, baudrate=BAUD, parity="N", stopbits=1, bytesize=8, samples=2, timeout=0.1
        )
    assert r.round_trips == [] and r.failures[0].startswith("no complete answer within 0.1 s")


def test_the_line_check_over_tcp() -> None:
    from pyrtu.tcp_server import TcpServer

    store = pyrtu.DataStore()
    store.holding_registers.add_range(0, [1, 2, 3])
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    server = TcpServer.for_store(1, store)
    asyncio.run_coroutine_threadsafe(server.start("127.0.0.1", 0), loop).result(10)
    assert server.address is not None
    try:
        r = check_tcp(f"tcp://127.0.0.1:{server.address[1]}", 1, count=3, samples=20)
    finally:
        asyncio.run_coroutine_threadsafe(server.close(), loop).result(10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()
    f = r.figures()
    assert f["transactions"] == 20 and "request_wire" not in f
    assert f["recommended_timeout"] >= 1.5 * f["round_trip_max"]


# -- the command ---------------------------------------------------------------------------


def test_bench_json_reports_every_backend_and_what_it_left_out() -> None:
    r = pyrtu_bench("--quick", "--parts", "crc,stream", "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert doc["machine"]["backend"] == pyrtu.BACKEND and doc["machine"]["cores"]
    groups = {row["group"] for row in doc["rows"]}
    assert groups == {"CRC-16 of 256 bytes", "parse_stream: 2000 transactions"}
    for group in groups:
        rows = {row["contender"]: row for row in doc["rows"] if row["group"] == group}
        c = rows["pyrtu (C core)"]
        assert c["vs_c"] == 1.0
        twin = rows["pyrtu (pure Python)"]
        assert twin["vs_c"] == pytest.approx(twin["seconds"] / c["seconds"])
        for row in rows.values():
            assert 0 < row["low"] <= row["seconds"] <= row["high"]
    crc_peers = {row["contender"] for row in doc["rows"] if row["group"].startswith("CRC")}
    named = crc_peers | {s["contender"] for s in doc["skipped"]}
    assert {"crcmod", "minimalmodbus"} <= named  # measured, or left out with a reason
    assert doc["line"] is None


def test_bench_table_and_a_line_check_of_a_device(tmp_path: Path) -> None:
    with device(0.005) as port:
        r = pyrtu_bench(
            "--parts",
            "none",
            "--port",
            port,
            "--slave",
            "7",
            "--parity",
            "N",
            "--count",
            "2",
            "--samples",
            "20",
        )
    assert r.returncode == 0, r.stderr
    assert (
        f"line check: {port}, slave 7, 2 holding register(s) at 0: 20 answered, 0 failed"
        in r.stdout
    )
    assert "round trip" in r.stdout and "recommended     timeout" in r.stdout
    assert "Traceback" not in r.stderr


def test_bench_html_has_the_plots(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "report.html"
    r = pyrtu_bench("--quick", "--parts", "master", "--html", str(out), timeout=180)
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert text.startswith("<!doctype html>") and text.count("<svg") == 2
    assert "master: read 10 registers" in text and "one transaction" in text
    assert "<script" not in text and "http" not in text.split("</style>")[0]  # self-contained


def test_html_without_matplotlib_is_refused_before_measuring(tmp_path: Path) -> None:
    code = (
        "import sys; sys.modules['matplotlib'] = None\n"
        "from pyrtu.cli import main\n"
        f"sys.exit(main(['bench', '--html', {str(tmp_path / 'r.html')!r}]))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env(), timeout=60
    )
    assert r.returncode == 2
    assert "--html needs matplotlib: pip install 'pyrtu[bench]'" in r.stderr
    assert "measuring" not in r.stderr and not (tmp_path / "r.html").exists()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--parts", "crc,nope"], "--parts"),
        (["--parts", "none"], "--parts none leaves nothing to do without --port"),
        (["--count", "0", "--port", "/dev/null"], "--count"),
        (["--count", "126", "--port", "/dev/null"], "--count"),
        (["--samples", "0"], "--samples"),
        (["--budget", "0"], "--budget"),
        (["--port", "/dev/ttyS0", "--slave", "0", "--parts", "none"], "--slave 0 is the broadcast"),
    ],
)
def test_bad_arguments_exit_2_naming_them(args: list[str], words: str) -> None:
    r = pyrtu_bench(*args)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert words in r.stderr and "Traceback" not in r.stderr
    assert "measuring" not in r.stderr


def test_a_port_that_does_not_exist_is_one_line_exit_3(tmp_path: Path) -> None:
    r = pyrtu_bench("--parts", "none", "--port", str(tmp_path / "nothing"), "--parity", "N")
    assert r.returncode == 3, (r.stdout, r.stderr)
    assert str(tmp_path / "nothing") in r.stderr and "Traceback" not in r.stderr
