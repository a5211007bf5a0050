"""The live table of ``pyrtu poll --config`` on a terminal.

Each refresh costs what fits on the screen, not what the configuration holds: the
points shown are the first that fit the terminal's height (in the file's order),
a line says how many more there are, and only the lines whose text changed since
the last refresh are rewritten.  A figure not known yet is shown as ``-``.  The
table is drawn by a `pyrtu.cli.live_view.LiveView`, through which the events of
the run are printed too (above the table, which is then drawn again below them).
"""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from pyrtu.cli.live_view import LiveView, Writer, terminal_size

if TYPE_CHECKING:
    from pyrtu.poller import Poller

#: the lines of buses and of slaves shown at most (each: a quarter of the screen)
_SHARE = 4


def fmt_value(value: object) -> str:
    """A value for people (floats to 6 significant digits; None, the device's "no
    value" marker: ``bad``)."""
    if value is None:
        return "bad"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def ms(value: float | None) -> str:
    """Milliseconds, or ``-`` when not known."""
    return "-" if value is None else f"{value:.1f} ms"


class LiveTable:
    """The table, redrawn in place on ``out`` (a terminal of ``size()``, by default
    the one ``out`` is written to)."""

    def __init__(
        self,
        poller: Poller,
        out: Writer,
        size: Callable[[], os.terminal_size] | None = None,
    ) -> None:
        self.poller = poller
        self.size = size if size is not None else terminal_size(out)
        self.view = LiveView(out, self.size)

    @property
    def shown(self) -> list[str]:
        """The lines on the screen, top to bottom."""
        return self.view.shown

    @property
    def written(self) -> int:
        """The lines written by the last `draw` (the changed ones)."""
        return self.view.written

    def frame(self, now: float | None = None) -> list[str]:
        """The lines to show, at most the terminal's height less one, each at most
        its width less one (a line that wraps would spoil the redraw)."""
        p = self.poller
        now = time.monotonic() if now is None else now
        cols, rows = self.size()
        height, width = max(3, rows - 1), max(20, cols - 1)
        buses = self._buses(now, max(1, height // _SHARE))
        slaves = self._slaves(max(1, height // _SHARE))
        room = max(0, height - len(buses) - len(slaves) - 2)
        points = p.config.points
        lines = [f"{'point':32} {'value':>14} {'age':>8}  slave  bus"]
        for point in itertools.islice(points, room):
            u = p.last(point.name)
            seconds = p.age(point.name)
            value = "-" if u is None else fmt_value(u.value)
            age = "-" if seconds is None else f"{seconds:.1f}s"
            lines.append(
                f"{point.name[:32]:32} {value[:14]:>14} {age:>8}  {point.slave:5}  {point.bus}"
            )
        more = len(points) - min(room, len(points))
        read = p.points_read()
        tail = f"{len(points)} points, {read} read"
        lines.append(tail + (f"; {more} more not shown (--json shows all)" if more else ""))
        return [line[:width] for line in lines + buses + slaves]

    def _buses(self, now: float, most: int) -> list[str]:
        p = self.poller
        out = []
        names = [b.name for b in p.config.buses]
        for name in names[:most]:
            sched = p.scheduler(name)
            load = sched.last_load
            out.append(
                f"bus {name}: port {p.port_state(name)}, utilisation "
                f"{sched.utilisation(now):.1%}, load {load:.2f}" + (" OVERLOAD" if load > 1 else "")
            )
        if len(names) > most:
            out.append(f"... {len(names) - most} more buses")
        return out

    def _slaves(self, most: int) -> list[str]:
        stats = self.poller.slave_stats()
        out = []
        for s in stats[:most]:
            state = {None: "unknown", True: "online", False: "offline"}[s.online]
            out.append(
                f"  slave {s.slave} on {s.bus}: {state}, {s.responses}/{s.requests} answered,"
                f" p50 {ms(_ms(s.latency(50)))}, p99 {ms(_ms(s.latency(99)))}"
            )
        if len(stats) > most:
            out.append(f"  ... {len(stats) - most} more slaves")
        return out

    def draw(self, now: float | None = None) -> None:
        """Rewrite the lines that changed (the cursor ends below the table)."""
        self.view.draw(self.frame(now))

    def print_above(self, text: str, stream: Writer | None = None) -> None:
        """``text`` above the table, which is drawn again below it."""
        self.view.print_above(text, stream)


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1e3


__all__ = ["LiveTable", "fmt_value", "ms"]
