"""``pyrtu poll --config``: JSON updates, events and the summary on the virtual bus,
exit statuses that say what came in, config errors with exit status 2 and no
traceback, ports that fail and come back, ends on time, on signals and on a closed
pipe, the live table on a terminal; the single-range form unchanged."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest
from cli_helpers import POLL_BUS, ROOT, Background, env, poll_weg, pyrtu
from peers.tools import free_tcp_port

from pyrtu.devices import CFW701Simulator, CV100Simulator, weg

vbus = pytest.importorskip("pyrtu.vbus")

CONFIG = (
    POLL_BUS
    + """
[[device]]
bus = "line1"
slave = 1
profile = "cfw701"
name = "weg"

[[point]]
name = "cv.status"
slave = 5
table = "holding"
address = 0x3300

[[point]]
name = "ghost.status"
slave = 9
table = "holding"
address = 0
"""
)


def split(docs: list[dict[str, object]]) -> tuple[list[dict[str, object]], ...]:
    """``--json`` lines: (updates, events, summaries)."""
    updates = [d for d in docs if "point" in d and "event" not in d]
    events = [d for d in docs if "event" in d]
    return updates, events, [d for d in docs if d.get("summary")]


def test_json_updates_events_and_summary(tmp_path: Path) -> None:
    with vbus.VirtualBus(3, baudrate=115200, parity="N") as bus:
        sim_weg, sim_cv = CFW701Simulator(), CV100Simulator()
        sim_weg.serve(bus.paths[1], 1, baudrate=115200, parity="N")
        sim_cv.serve(bus.paths[2], 5, baudrate=115200, parity="N")
        try:
            cfg = tmp_path / "points.toml"
            # cv.status every millisecond: more than the wire carries (an overload);
            # weg.missing does not exist (dropped); slave 9 is not there (offline)
            text = CONFIG.format(port=bus.paths[0]).replace(
                "address = 0x3300\n", "address = 0x3300\ninterval = 0.001\n"
            )
            text += '[[point]]\nname = "weg.missing"\nslave = 1\ntable = "holding"\n'
            text += "address = 2900\n"
            cfg.write_text(text)
            r = pyrtu("poll", "--config", cfg, "--duration", "3", "--json")
        finally:
            sim_weg.close()
            sim_cv.close()
    # slave 9 never answered: 4, the most telling of the statuses that apply
    assert r.code == 4, r.err
    assert r.err.strip() == "pyrtu poll: exit status 4: bus line1: slave 9 offline at the end"
    updates, events, (summary,) = split(r.json_lines())
    assert r.json_lines()[-1] is not None and r.out.splitlines()[-1].startswith('{"summary"')
    names = {u["point"] for u in updates}
    assert names == {"weg.status", "weg.speed", "weg.current", "weg.fault", "weg.alarm",
                     "cv.status"}  # fmt: skip
    for u in updates:
        assert set(u) == {"point", "value", "time", "slave", "bus"} and u["bus"] == "line1"
    status = next(u for u in updates if u["point"] == "weg.status")
    assert status["value"] == CFW701Simulator().store.holding_registers.get(weg.P_STATUS)
    # every event, as a line of its own
    kinds = Counter(str(e["event"]) for e in events)
    assert kinds["slave"] == 3 and kinds["dropped"] == 1 and kinds["overload"] >= 1, kinds
    slave_events = [(e["slave"], e["online"]) for e in events if e["event"] == "slave"]
    assert sorted(slave_events) == [(1, True), (5, True), (9, False)]
    (dropped,) = [e for e in events if e["event"] == "dropped"]
    assert dropped["point"] == "weg.missing" and "exception 2" in str(dropped["reason"])
    overload = next(e for e in events if e["event"] == "overload")
    assert overload["overloaded"] is True and overload["load"] > 1  # type: ignore[operator]
    # the summary counts the update lines it printed, and every value read apart
    assert summary["updates"] == len(updates)
    assert summary["values_read"] > len(updates)  # change-only: most reads repeat
    assert summary["dropped_points"] == ["weg.missing"] and summary["points_unread"] == 1
    (b,) = summary["buses"]  # type: ignore[misc]
    assert 0 < b["utilisation"] <= 1 and b["transactions"] > 10
    assert b["port_state"] == "up" and b["outages"] == 0
    slaves = {s["slave"]: s for s in summary["slaves"]}  # type: ignore[attr-defined]
    assert slaves[1]["state"] == slaves[5]["state"] == "online"
    assert slaves[9]["state"] == "offline" and slaves[9]["timeouts"] >= 2
    assert slaves[9]["responses"] == 0
    assert "Traceback" not in r.err


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            '[[bus]]\nname = 1\nport = "{port}"\n',
            "points.toml:2: bus[0]: name: must be a non-empty",
        ),
        ("[[bus]]\nname = 1\n", "points.toml:1: bus[0]: port: missing"),
        (CONFIG.replace("0x3300", "-1"), 'points.toml:23: point[0] ("cv.status"): address:'),
        (CONFIG.replace("slave = 9", "slave = 300"), "slave: must be an integer 1..247 on serial"),
        ("[[bus]\n", "points.toml: "),
    ],
)
def test_config_errors_exit_2_before_any_port_opens(
    tmp_path: Path, text: str, message: str
) -> None:
    cfg = tmp_path / "points.toml"
    # the port does not exist: a config error must be reported before opening it
    cfg.write_text(text.replace("{port}", "/nonexistent/ttyX"))
    r = pyrtu("poll", "--config", cfg, "--json")
    assert r.code == 2, (r.out, r.err)
    assert r.err.startswith("pyrtu poll: config error: ") and message in r.err
    assert "Traceback" not in r.err and "nonexistent" not in r.err
    # --json: the error as the README shows errors, one object on stdout (#27.14)
    doc = r.json()
    assert {k: doc[k] for k in ("ok", "error", "exit_code")} == {
        "ok": False,
        "error": "usage",
        "exit_code": 2,
    }
    assert doc["message"] == r.err.strip().removeprefix("pyrtu poll: ")
    without = pyrtu("poll", "--config", cfg)  # for people only: stdout stays empty
    assert without.code == 2 and without.out == "" and without.err == r.err


def test_missing_file_and_missing_port(tmp_path: Path) -> None:
    r = pyrtu("poll", "--config", tmp_path / "none.toml")
    assert r.code == 2 and "none.toml: no such file" in r.err and "Traceback" not in r.err
    cfg = tmp_path / "points.toml"
    cfg.write_text(CONFIG.format(port="/nonexistent/ttyX"))
    r = pyrtu("-v", "poll", "--config", cfg, "--duration", "1")
    assert r.code == 3 and "/nonexistent/ttyX" in r.err and "Traceback" not in r.err
    r = pyrtu("poll", "--config", cfg, "--duration", "-1")
    assert r.code == 2 and "--duration" in r.err


def test_single_range_form_still_works(tmp_path: Path) -> None:
    """The old form reads a drive: P0100 and P0101 of a CFW701 on the virtual bus
    (acceleration and deceleration times, whose factory defaults the manual gives as
    5.0 s and 10.0 s: 50 and 100 in 0.1 s), and reports them in its final line."""
    with Served(tmp_path) as s:
        assert (s.sim.get(100), s.sim.get(101)) == (50, 100)  # the simulated drive's
        r = pyrtu(
            "poll", s.bus.paths[0], "100", "2", "-a", "1", "-n", "3", "-r", "0",
            "-b", "115200", "-P", "N", "--json", timeout=60,
        )  # fmt: skip
    assert r.code == 0, (r.out, r.err)
    final = r.json_lines()[-1]
    assert final["final"] is True and final["slave"] == 1
    assert final["values"] == [50, 100] and final["addresses"] == [100, 101]
    total = final["total"]
    assert isinstance(total, dict) and (total["transactions"], total["ok"]) == (3, 3)
    assert total["errors"] == {}
    # loop:// sends the request back: a frame error (6), reported by the old command
    r = pyrtu("poll", "loop://", "0", "--count", "1", "--timeout", "0.05", "--json")
    assert r.code == 6 and '"final": true' in r.out


GOOD = poll_weg(timeout=1.0)


class Served:
    """A virtual bus with a CFW701 at 1 on drop 1; the poller's drop is drop 0."""

    def __init__(self, tmp_path: Path, extra: str = "") -> None:
        self.bus = vbus.VirtualBus(2, baudrate=115200, parity="N")
        self.sim = CFW701Simulator()
        self.config = tmp_path / "points.toml"
        self.extra = extra

    def __enter__(self) -> Served:
        self.bus.start()
        self.sim.serve(self.bus.paths[1], 1, baudrate=115200, parity="N")
        self.config.write_text(GOOD.format(port=self.bus.paths[0]) + self.extra)
        return self

    def __exit__(self, *exc: object) -> None:
        self.sim.close()
        self.bus.close()


@pytest.mark.wall_clock
@pytest.mark.parametrize("duration", [1, 2, 3])
def test_a_refusing_tcp_bus_ends_on_time_with_status_3(tmp_path: Path, duration: int) -> None:
    """The durations on the beat of the points' interval (1 s) and of the refused
    connections hung: the run must end within its duration and one timeout."""
    cfg = tmp_path / "tcp.toml"
    cfg.write_text(
        f'[[bus]]\nname = "t"\nport = "tcp://127.0.0.1:{free_tcp_port()}"\n\n'
        '[[point]]\nname = "x"\nbus = "t"\nslave = 1\ntable = "holding"\naddress = 0\n'
    )
    start = time.monotonic()
    # bound: the duration, one timeout (1 s) and the interpreter's start on a loaded VM
    r = pyrtu("poll", "--config", cfg, "--duration", duration, "--json", timeout=duration + 15)
    assert time.monotonic() - start < duration + 15
    assert r.code == 3, (r.out, r.err)
    updates, events, (summary,) = split(r.json_lines())
    assert updates == [] and [(e["event"], e["up"]) for e in events] == [("port", False)]
    assert "cannot connect" in str(events[0]["error"])
    assert summary["buses"][0]["port_state"] == "down"  # type: ignore[index]
    assert "exit status 3: bus t: port tcp://127.0.0.1:" in r.err and "Traceback" not in r.err


def test_a_port_unplugged_mid_run_is_reported_once_and_reopened(tmp_path: Path) -> None:
    with Served(tmp_path) as s:
        port = s.bus.paths[0]
        bg = Background("-v", "poll", "--config", s.config, "--duration", "6", "--all")
        try:
            bg.line(timeout=15)  # polling
            s.bus.unplug(0)

            def err_with(text: str) -> bool:
                give_up = time.monotonic() + 15
                while time.monotonic() < give_up:
                    if text in "".join(bg.err):
                        return True
                    time.sleep(0.05)
                return False

            assert err_with("down"), bg.err
            time.sleep(1.0)  # attempts at 0.1, 0.2, 0.4 s... fail: not reported again
            s.bus.replug(0)
            assert err_with("back after"), bg.err
            r = bg.finish(timeout=20)
        finally:
            bg.kill()
    assert r.code == 0, r.err
    shown = [line for line in r.err.splitlines() if f"port {port}" in line]
    # one message of the command, one log line (-v) for each of the two changes
    assert len(shown) == 4, shown
    assert sum("down" in line for line in shown) == 2
    assert sum("back after" in line for line in shown) == 2
    assert "offline" not in r.err and "Traceback" not in r.err
    assert f"bus line1 ({port}): port up, 1 outages" in r.out
    assert "0 timeouts" in r.out


def test_a_port_down_at_the_end_exits_3_and_dropped_points_5(tmp_path: Path) -> None:
    with Served(tmp_path) as s:
        bg = Background("poll", "--config", s.config, "--duration", "2", "--json")
        try:
            bg.line(timeout=15)
            s.bus.unplug(0)
            r = bg.finish(timeout=20)
        finally:
            bg.kill()
    assert r.code == 3, r.err
    _, events, (summary,) = split(r.json_lines())
    assert [(e["event"], e.get("up")) for e in events] == [("slave", None), ("port", False)]
    assert summary["buses"][0]["port_state"] == "down"  # type: ignore[index]
    assert "exit status 3" in r.err
    missing = '[[point]]\nname = "weg.missing"\nbus = "line1"\nslave = 1\n'
    missing += 'table = "holding"\naddress = 2900\n'
    with Served(tmp_path, missing) as s:
        r = pyrtu("poll", "--config", s.config, "--duration", "1.5", "--json")
    assert r.code == 5, r.err
    assert "exit status 5: points dropped: weg.missing" in r.err


@pytest.mark.wall_clock
@pytest.mark.parametrize("options", [["--all"], ["--all", "--json"], [], ["--json"]])
def test_a_closed_pipe_ends_it_at_once_with_status_0(tmp_path: Path, options: list[str]) -> None:
    """``| head -1``: the reader goes away after one line; without ``--all`` nothing
    more is written for a while (the values do not change), so the command must
    see the pipe close, not wait for a write to fail."""
    with Served(tmp_path) as s:
        args = [sys.executable, "-m", "pyrtu", "poll", "--config", str(s.config)]
        args += ["--duration", "25", *options]
        start = time.monotonic()
        proc = subprocess.Popen(
            args, cwd=ROOT, env=env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        assert proc.stdout is not None
        first = proc.stdout.readline()
        proc.stdout.close()  # what head does after its line
        try:
            code = proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
        err = proc.stderr.read().decode() if proc.stderr else ""
    assert first
    # bound: far below the 25 s duration (the interpreter's start on a loaded VM)
    assert time.monotonic() - start < 15
    assert code == 0, err
    assert "Traceback" not in err and "Broken pipe" not in err and "BrokenPipe" not in err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signals_end_it_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    with Served(tmp_path) as s:
        bg = Background("poll", "--config", s.config, "--json")
        try:
            bg.line(timeout=15)
            time.sleep(0.5)
            bg.proc.send_signal(sig)
            r = bg.finish(timeout=20)
        finally:
            bg.kill()
    assert r.code == 0, r.err  # every point read, the port and the slave up
    assert r.json_lines()[-1]["summary"] is True
    assert r.err == ""


def test_the_live_table_fits_the_terminal(tmp_path: Path) -> None:
    """10 000 points on a 24-line terminal: each refresh draws at most 23 lines, and
    no figure shows as None."""
    import fcntl
    import pty
    import struct
    import termios

    extra = "".join(
        f'[[point]]\nname = "ghost.{i}"\nbus = "line1"\nslave = 9\ntable = "holding"\n'
        f"address = {i}\ninterval = 5.0\n"
        for i in range(10_000)
    )
    with Served(tmp_path, extra) as s:
        master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
        e = env()
        e.pop("COLUMNS", None)
        e.pop("LINES", None)
        proc = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", "poll", "--config", str(s.config),
             "--duration", "3", "--refresh", "0.2"],
            cwd=ROOT, env=e, stdin=slave, stdout=slave, stderr=subprocess.PIPE,
        )  # fmt: skip
        os.close(slave)
        chunks = []
        try:
            while True:
                try:
                    data = os.read(master, 65536)
                except OSError:  # EIO: the child closed the terminal
                    break
                if not data:
                    break
                chunks.append(data)
            code = proc.wait(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
            os.close(master)
    out = b"".join(chunks).decode()
    assert code == 4  # slave 9 does not answer
    assert "None" not in out
    table = out.partition("updates delivered")[0]
    frames = [f for f in table.split("\x1b[") if f.startswith(("23F", "22F", "21F"))]
    assert frames, "the table was not redrawn"
    # the first frame: every line at most 79 characters, 23 lines at most
    first = table.split("\x1b[23F")[0].split("\x1b[2K")[1:]
    assert 3 <= len(first) <= 23
    assert all(len(line.rstrip("\r\n")) <= 79 for line in first)
    assert "10005 points" in table and "more not shown" in table
    assert "p50 -" in table and "slave 9 on line1" in table
