"""The live table of ``pyrtu poll --config``: what fits the terminal, bounded work
per refresh whatever the number of points, only changed lines rewritten, ``-`` for
what is not known yet (never ``None``)."""

from __future__ import annotations

import io
import os

from pyrtu.cli.poll_table import LiveTable
from pyrtu.poller import Bus, Point, Poller, make_config
from pyrtu.poller.events import Update


def big_poller(n: int = 10_000) -> Poller:
    buses = [Bus("line1", "/nonexistent/ttyX", {"baudrate": 19200, "parity": "N"})]
    points = [Point(f"p{i}", "line1", 1 + i % 4, "holding", i // 4) for i in range(n)]
    return Poller(make_config(buses, points))


def test_a_frame_is_what_fits_the_terminal_and_never_none() -> None:
    poller = big_poller()
    asked: list[str] = []
    last = poller.last

    def counting_last(name: str) -> Update | None:
        asked.append(name)
        return last(name)

    poller.last = counting_last  # type: ignore[method-assign]
    size = [os.terminal_size((80, 24))]
    table = LiveTable(poller, io.StringIO(), lambda: size[0])
    lines = table.frame()
    assert len(lines) <= 23 and all(len(line) <= 79 for line in lines)
    assert len(asked) <= 23  # the points shown, not the 10 000
    text = "\n".join(lines)
    assert "None" not in text
    assert "10000 points, 0 read" in text and "more not shown" in text
    assert "slave 1 on line1: unknown, 0/0 answered, p50 -, p99 -" in text
    assert "bus line1: port unknown" in text
    # a taller and wider terminal shows more, still bounded by it
    size[0] = os.terminal_size((200, 60))
    assert 23 < len(table.frame()) <= 59


def test_a_redraw_rewrites_only_what_changed() -> None:
    poller = big_poller(100)
    out = io.StringIO()
    size = [os.terminal_size((80, 24))]
    table = LiveTable(poller, out, lambda: size[0])
    table.draw(now=0.0)
    first = out.getvalue()
    assert table.written == len(table.shown) <= 23
    assert first.count("\x1b[2K") == table.written
    table.draw(now=0.0)  # nothing changed: the cursor moves over the lines
    second = out.getvalue()[len(first) :]
    assert table.written == 0 and "\x1b[2K" not in second
    assert second.startswith(f"\x1b[{len(table.shown)}F")
    # a smaller terminal: fewer lines, drawn whole on a cleared screen (a terminal
    # that reflows its text on a resize moved the old lines where no count finds them)
    size[0] = os.terminal_size((80, 12))
    before = len(out.getvalue())
    table.draw(now=0.0)
    third = out.getvalue()[before:]
    assert len(table.shown) <= 11 and third.startswith("\x1b[H\x1b[J")
    assert table.written == len(table.shown)
