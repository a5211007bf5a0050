"""Every live view fits the terminal it is drawn on, and owns it while it is shown.

The commands run on pseudo-terminals of several sizes; what they write is fed to a
terminal emulator (pyte), which is the judge of what a user sees: no row ever
reaches the last column (where a terminal wraps it and the next redraw, counting
one row per line, leaves its remains behind), each line of a view appears once
on the screen and in the scrollback (no frozen copies), and every event printed
while the view is shown is still there to read.
"""

from __future__ import annotations

import io
import os
import re
from pathlib import Path

import pytest
from cli_helpers import POLL_BUS
from term_screen import Terminal

from pyrtu.cli.live_view import LiveView, columns, fit_line
from pyrtu.devices import CFW701Simulator, CV100Simulator

vbus = pytest.importorskip("pyrtu.vbus")

SIZES = [(80, 24), (40, 10), (200, 50)]

#: a row of the demo's view (cut or not): the slave address and the drive
DEMO_ROW = re.compile(r"^\s+(\d) (WEG CFW701|WEG CFW100|Bonfiglioli ACU|CV100)\s+[\d.-]")


def count(lines: list[str], pattern: re.Pattern[str], group: int = 2) -> dict[str, int]:
    """How many of ``lines`` match ``pattern``, by what its ``group`` matched."""
    found: dict[str, int] = {}
    for line in lines:
        m = pattern.match(line)
        if m is not None:
            found[m.group(group)] = found.get(m.group(group), 0) + 1
    return found


# -- the drawing rules, at their boundaries -------------------------------------------


def test_a_line_is_cut_to_the_width_its_escapes_taking_no_room() -> None:
    assert fit_line("abcdef", 6) == "abcdef"  # exactly the width: kept whole
    assert fit_line("abcdefg", 6) == "abcdef"  # one more: cut
    bold = "\x1b[1mabc\x1b[0mdef"
    assert columns(bold) == 6
    assert fit_line(bold, 6) == bold  # escapes take no columns
    assert fit_line(bold, 4) == "\x1b[1mabc\x1b[0md\x1b[0m"  # cut: attributes reset
    assert columns("\u6e29\u5ea6") == 4  # wide characters take two columns
    assert fit_line("\u6e29\u5ea6x", 3) == "\u6e29"  # never half a wide character


def test_a_frame_is_cut_to_the_height_less_one_row() -> None:
    out = io.StringIO()
    view = LiveView(out, lambda: os.terminal_size((10, 5)))
    assert view.fit(["a"] * 4) == ["a"] * 4  # rows - 1: all of it
    five = view.fit([str(i) for i in range(5)])
    assert len(five) == 4 and five[:3] == ["0", "1", "2"]
    assert five[3] == "... 2 mor"  # "... 2 more lines ...", cut to 9 columns
    assert all(columns(line) <= 9 for line in view.fit(["x" * 50] * 50))


def test_a_redraw_rewrites_what_changed_and_clears_what_a_shorter_frame_left() -> None:
    out = io.StringIO()
    view = LiveView(out, lambda: os.terminal_size((20, 10)))
    view.draw(["a", "b", "c"])
    assert out.getvalue() == "\x1b[2Ka\n\x1b[2Kb\n\x1b[2Kc\n"
    out.truncate(0)
    out.seek(0)
    view.draw(["a", "B"])  # up 3 lines, a kept, b rewritten, the rest cleared
    assert out.getvalue() == "\x1b[3F\x1b[1E\x1b[2KB\n\x1b[J"
    assert view.written == 1
    out.truncate(0)
    out.seek(0)
    view.print_above("event")  # the frame off, the line, the frame whole again
    assert out.getvalue() == "\x1b[2F\x1b[Jevent\n\x1b[2Ka\n\x1b[2KB\n"


# -- pyrtu demo -------------------------------------------------------------------------


@pytest.mark.parametrize(("width", "height"), SIZES)
def test_demo_fits_the_terminal(width: int, height: int) -> None:
    term = Terminal(width, height)
    term.start("demo", "--duration", "3", "--accel", "2")
    code = term.finish()
    assert code == 0, "\n".join(term.everything())
    # while the view was shown, no row ever reached the last column
    assert term.wrapped(b"\x1b[?25l", b"\x1b[?25h") == []
    seen = term.everything()
    rows = count(seen, DEMO_ROW)
    # each drive's row once: the view redrawn in place, no copies left behind
    assert rows == {"WEG CFW701": 1, "WEG CFW100": 1, "Bonfiglioli ACU": 1, "CV100": 1}, seen
    assert sum(line.startswith("t = ") for line in seen) == 1, seen
    assert any(line.startswith("bus: ") and "transactions" in line for line in seen), seen


def test_demo_follows_a_resized_terminal() -> None:
    term = Terminal(100, 30)
    term.start("demo", "--duration", "4", "--accel", "2")
    try:
        assert term.pump(60, lambda: b"\x1b[7F" in term.raw), "no redraw came"
        resized = len(term.raw)
        term.resize(45, 12)
        code = term.finish()
    finally:
        term.close()
    assert code == 0
    # what was on its way when the size changed was drawn for the old size; from the
    # redraw on the new size (the screen cleared, the frame drawn whole), no wrap
    redrawn = term.raw.find(b"\x1b[H\x1b[J", resized)
    assert redrawn > 0, "the view never redrew itself on the new size"
    end = term.raw.rfind(b"\x1b[?25h")
    assert [t for at, t in term.touched_last_column if redrawn <= at < end] == []
    # every drive is shown, and never twice on the screen; the frame drawn for the old
    # size may stay in the scrollback (a real terminal keeps what shrinking pushed up)
    drives = {"WEG CFW701", "WEG CFW100", "Bonfiglioli ACU", "CV100"}
    assert set(count(term.everything(), DEMO_ROW)) == drives
    assert all(n <= 1 for n in count(term.display(), DEMO_ROW).values()), term.display()


# -- pyrtu poll --config ------------------------------------------------------------------

POINTS = (
    POLL_BUS
    + """
[[point]]
name = "weg.status"
slave = 1
table = "holding"
address = 680

[[point]]
name = "weg.speed"
slave = 1
table = "holding"
address = 2

[[point]]
name = "weg.reference"
slave = 1
table = "holding"
address = 683

[[point]]
name = "cv.status"
slave = 5
table = "holding"
address = 0x3300

[[point]]
name = "cv.frequency"
slave = 5
table = "holding"
address = 0x3301
"""
)

NAMES = ("weg.status", "weg.speed", "weg.reference", "cv.status", "cv.frequency")
POINT_ROW = re.compile(r"^((weg|cv)\.\w+) ")


def point_rows(lines: list[str]) -> dict[str, int]:
    return count(lines, POINT_ROW, 1)


def event_lines(text: str) -> list[str]:
    """The event lines the command wrote (``pyrtu poll: ...``, not the exit status)
    and its log lines (``-v``: ``123.4 ms pyrtu.poller: ...``)."""
    events = [
        line
        for line in re.findall(r"pyrtu poll: [^\r\n\x1b]*", text)
        if not line.startswith("pyrtu poll: exit status")
    ]
    return events + re.findall(r" *\d+\.\d ms pyrtu[\w.]*: [^\r\n\x1b]*", text)


@pytest.mark.parametrize(("width", "height"), [(100, 30), (40, 10)])
def test_poll_config_events_are_printed_above_the_table(
    tmp_path: Path, width: int, height: int
) -> None:
    """A slave goes offline and the port is unplugged and plugged back while the
    table is redrawn every 50 ms: every event line and log line (-v) stays
    readable, every point's row is on the terminal once."""
    with vbus.VirtualBus(3, baudrate=115200, parity="N") as bus:
        weg, cv = CFW701Simulator(), CV100Simulator()
        weg.serve(bus.paths[1], 1, baudrate=115200, parity="N")
        cv.serve(bus.paths[2], 5, baudrate=115200, parity="N")
        config = tmp_path / "points.toml"
        config.write_text(POINTS.format(port=bus.paths[0]))
        term = Terminal(width, height)
        try:
            term.start(
                "-v", "poll", "--config", config, "--duration", "5", "--refresh", "0.05"
            )  # -v: pyrtu's log lines on the terminal too
            assert term.pump(30, lambda: b"points, " in term.raw), "no table came"
            cv.close()  # slave 5 offline
            assert term.pump(15, lambda: b"slave 5 offline" in term.raw)
            bus.unplug(0)  # the port down, then back
            assert term.pump(15, lambda: b"down" in term.raw)
            bus.replug(0)
            code = term.finish()
        finally:
            term.close()
            weg.close()
    assert code == 4  # slave 5 offline at the end
    seen = term.everything()
    text = "\n".join(seen)
    events = event_lines(term.raw.decode("utf-8", "replace"))
    # while the table was shown, no row of it reached the last column (the event
    # lines above it are printed whole: they may wrap, they are not redrawn)
    wrapped = term.wrapped(b"points, ", b"updates delivered")
    assert [row for row in wrapped if not any(row.strip() in e for e in events)] == []
    assert any("slave 5 offline" in e for e in events), events
    assert any(" ms pyrtu" in e for e in events), events  # log lines came too
    assert any("down" in e for e in events) and any("back after" in e for e in events), events
    for event in events:  # every event line is still there (cut by no redraw)
        assert event[: width - 1] in text, (event, seen)
    rows = point_rows(seen)
    assert all(n == 1 for n in rows.values()), seen  # no frozen copies
    if height >= 30:
        assert set(rows) == set(NAMES), seen  # none missing on a terminal they fit


# -- pyrtu poll PORT ADDRESS (one range, a report line redrawn in place) ------------------


@pytest.mark.parametrize(("width", "height"), SIZES)
def test_poll_report_line_fits_the_terminal(width: int, height: int) -> None:
    with vbus.VirtualBus(2, baudrate=115200, parity="N") as bus:
        weg = CFW701Simulator()
        weg.serve(bus.paths[1], 1, baudrate=115200, parity="N")
        term = Terminal(width, height)
        try:
            term.start(
                "poll", bus.paths[0], "680", "4", "--parity", "N", "--baudrate", "115200",
                "--duration", "2.5", "--interval", "0.2",
            )  # fmt: skip
            code = term.finish()
        finally:
            term.close()
            weg.close()
    assert code == 0, "\n".join(term.everything())
    start = term.raw.find(b"tx/s")  # the first report (its figures' unit)
    assert start >= 0, term.raw.decode(errors="replace")
    final = term.raw.find(b" transactions in ", start)  # the final line (plain)
    assert [t for at, t in term.touched_last_column if start <= at < final] == []
    # the report was redrawn in place: one report line left above the final one
    reports = [line for line in term.everything() if "tx/s" in line]
    assert 1 <= len(reports) <= 2, term.everything()
