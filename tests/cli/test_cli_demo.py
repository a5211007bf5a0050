"""``pyrtu demo`` end to end: it runs to completion by itself with exit 0, identifies
the four drives, and the CFW701 ramps to 30 Hz; plain lines when the output is not a
terminal, a view redrawn in place with ANSI escapes when it is (a pseudo-terminal)."""

from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
import time

import pytest
from cli_helpers import ROOT, env, pyrtu

#: a row of the plain output: [time] slave drive frequency word-name 0xWORD status
ROW = re.compile(
    r"^\s*(?:[\d.]+ s)?\s+(\d+) (WEG CFW701|WEG CFW100|Bonfiglioli ACU|CV100)\s+"
    r"([\d.]+) Hz\s+(\S+) 0x([0-9A-F]{4}) (.*)$"
)


@pytest.mark.wall_clock
def test_demo_plain_lines_reach_30_hz() -> None:
    t0 = time.monotonic()
    r = pyrtu("demo", "--duration", "5", "--accel", "4", "--interval", "0.5", timeout=60)
    elapsed = time.monotonic() - t0
    assert r.code == 0, r.err
    # It runs for its duration (5 s), and then stops: 6 durations leave 25 s for the
    # start (a bus, four simulators) on a loaded 2-core VM, where it takes ~2 s.
    assert 5 <= elapsed < 6 * 5
    out = r.out
    assert "\x1b[" not in out  # not a terminal: no escapes
    # identification: FC 43 for the WEG drives, the profiles for the others
    assert re.search(r"slave 1: WEG CFW701 V\d\.\d\d\s+\(FC 43\)", out)
    assert re.search(r"slave 2: WEG CFW100 V\d\.\d\d\s+\(FC 43\)", out)
    assert re.search(r"slave 3: .*model ACU.*\(profile", out)
    assert re.search(r"slave 5: slave model \d+.*\(profile", out)
    assert "P683 = 4096" in out  # 30 Hz on the 13-bit scale of 60 Hz
    rows = [m.groups() for line in out.splitlines() if (m := ROW.match(line))]
    by_drive: dict[str, list[tuple[float, str, str]]] = {}
    for _, drive, hz, word, _, status in rows:
        by_drive.setdefault(drive, []).append((float(hz), word, status))
    assert set(by_drive) == {"WEG CFW701", "WEG CFW100", "Bonfiglioli ACU", "CV100"}
    cfw = by_drive["WEG CFW701"]
    assert len(cfw) >= 8  # a block every 0.5 s for 5 s
    speeds = [hz for hz, _, _ in cfw]
    assert any(0 < hz < 29 for hz in speeds), speeds  # the ramp is seen
    assert speeds == sorted(speeds)  # accelerating, then steady
    assert abs(speeds[-1] - 30.0) < 0.2
    assert cfw[-1][1] == "P680" and cfw[-1][2] == "running, forward, remote"
    assert by_drive["Bonfiglioli ACU"][-1][1:] == ("411", "starting lockout, remote")
    assert by_drive["CV100"][-1][1:] == ("SW1", "stopped, forward")
    assert by_drive["WEG CFW100"][-1][0] == 0.0
    assert re.search(r"the CFW701 reached 30 Hz [\d.]+ s after the start", out)
    assert re.search(r"bus: \d+ transactions \(\d+/s\), 0 errors", out)
    # the newcomer's next step: a pyrtu command that runs from here (after make demo
    # the virtual environment is not activated: .venv/bin/pyrtu, not a bare pyrtu)
    hint = re.search(r'^next: (.+) --help; the same bus by hand: (\S+), "(.+)"$', r.err, re.M)
    assert hint, r.err
    assert hint.group(3) in (ROOT / hint.group(2)).read_text()  # the page says it
    version = subprocess.run(
        [*hint.group(1).split(), "--version"], cwd=ROOT, env=env(), capture_output=True, text=True
    )
    assert version.returncode == 0 and version.stdout.startswith("pyrtu "), version


def test_demo_live_view_on_a_terminal() -> None:
    master, slave = pty.openpty()
    proc = subprocess.Popen(
        [sys.executable, "-m", "pyrtu", "demo", "--duration", "2", "--accel", "2"],
        cwd=ROOT,
        env={**env(), "TERM": "xterm"},
        stdin=subprocess.DEVNULL,
        stdout=slave,
        stderr=subprocess.PIPE,
    )
    os.close(slave)
    data = bytearray()
    deadline = time.monotonic() + 40
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.5)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:  # EIO: the child closed the terminal
                    break
                if not chunk:
                    break
                data += chunk
            elif proc.poll() is not None:
                break
        code = proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        os.close(master)
    text = data.decode("utf-8", "replace")
    assert code == 0, proc.stderr.read() if proc.stderr else ""
    assert "\x1b[?25l" in text and "\x1b[?25h" in text  # cursor hidden, then shown again
    redraws = re.findall(r"\x1b\[(\d+)F", text)
    assert len(redraws) >= 3 and set(redraws) == {"7"}  # the 7-line view, redrawn in place
    assert text.count("\x1b[2K") >= 7 * 4
    assert "[####" in text  # the CFW701's bar
    assert "the CFW701 reached 30 Hz" in text
