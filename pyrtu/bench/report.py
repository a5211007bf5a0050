"""What `pyrtu bench` shows: a table on the terminal, a JSON document for machines,
and a self-contained HTML report with plots (a histogram of the transactions'
latencies, the time line of one transaction on the wire).  The plots are drawn with
matplotlib, the optional extra ``pyrtu[bench]``; `plotting_available` says whether it
is installed (the command checks before it measures anything)."""

from __future__ import annotations

import html
import io
import os
import platform
import sys
import time
from typing import Any

from pyrtu.bench.line import LineReport
from pyrtu.bench.suite import Row, SuiteResult

REFERENCE = "pyrtu (C core)"


def machine() -> dict[str, Any]:
    """The machine the figures come from."""
    from pyrtu._version import __version__
    from pyrtu.core._backend import active

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "system": f"{platform.system()} {platform.release()}",
        "python": sys.version.split()[0],
        "pyrtu": __version__,
        "backend": active.BACKEND,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }


def human(seconds: float) -> str:
    """A duration in the unit that keeps 3 significant digits readable."""
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6)):
        if abs(seconds) >= scale:
            return f"{seconds / scale:.3g} {unit}"
    return f"{seconds / 1e-9:.3g} ns"


def ratio(row: Row, rows: list[Row]) -> float | None:
    """``row``'s time over the C core's in the same group (None without one)."""
    for r in rows:
        if r.group == row.group and r.contender == REFERENCE and r.seconds > 0:
            return row.seconds / r.seconds
    return None


def groups(rows: list[Row]) -> list[str]:
    return list(dict.fromkeys(r.group for r in rows))


def as_json(suite: SuiteResult | None, line: LineReport | None) -> dict[str, Any]:
    out: dict[str, Any] = {"machine": machine()}
    if suite is not None:
        out["rows"] = [dict(r.as_dict(), vs_c=ratio(r, suite.rows)) for r in suite.rows]
        out["skipped"] = [{"group": g, "contender": c, "why": w} for g, c, w in suite.skipped]
        out["vbus_line"] = suite.vbus_line.figures() if suite.vbus_line else None
    out["line"] = line.figures() if line is not None else None
    return out


def table(suite: SuiteResult | None, line: LineReport | None) -> str:
    m = machine()
    out = [
        f"pyrtu {m['pyrtu']} (backend {m['backend']}) on {m['cpu']}, {m['cores']} cores, "
        f"{m['system']}, Python {m['python']}"
    ]
    if suite is not None:
        for group in groups(suite.rows):
            rows = [r for r in suite.rows if r.group == group]
            out.append("")
            out.append(f"{group} (per {rows[0].unit}; median, fastest-slowest batch)")
            for r in rows:
                x = ratio(r, suite.rows)
                vs = f"{x:7.2f}x C" if x is not None else ""
                extra = ""
                if "p99" in r.extra:
                    extra = f"  p99 {human(r.extra['p99'])}, CPU {human(r.extra['cpu'])}"
                out.append(
                    f"  {r.contender:22} {human(r.seconds):>10}  "
                    f"({human(r.low)}-{human(r.high)}) {vs}{extra}"
                )
            for g, c, why in suite.skipped:
                if g == group:
                    out.append(f"  {c:22} not measured: {why}")
    if line is not None:
        out.append("")
        out.extend(line_lines(line))
    return "\n".join(out) + "\n"


def line_lines(line: LineReport) -> list[str]:
    f = line.figures()
    out = [
        f"line check: {f['port']}, slave {f['slave']}, {f['count']} {f['table']} register(s) "
        f"at {f['address']}: {f['transactions']} answered, {f['failures']} failed"
    ]
    if line.failures:
        out.append(f"  first failure: {line.failures[0]}")
    if not f["transactions"]:
        return out
    out.append(
        f"  round trip      p50 {human(f['round_trip_p50'])}, p99 {human(f['round_trip_p99'])}, "
        f"max {human(f['round_trip_max'])}"
    )
    if "char" in f:
        out.append(
            f"  on the wire     request {human(f['request_wire'])}, "
            f"answer {human(f['answer_wire'])} "
            f"({f['baudrate']} baud, {human(f['char'])} a character)"
        )
        out.append(
            f"  answer starts   {human(f['answer_start_p50'])} after the request was sent (p50; "
            f"min {human(f['answer_start_min'])}): the device's turnaround plus the adapter's "
            "receive latency"
        )
        out.append(
            f"  sending lag     {human(f['sending_lag_p50'])} (p50) beyond the request's wire time"
        )
        batching = (
            f"holds bytes: at least {human(f['batching_p50'])} added (p50), "
            f"{f['reads_per_answer_p50']:g} read(s) per answer"
            if f["batches"]
            else f"forwards bytes as they come ({f['reads_per_answer_p50']:g} reads per answer)"
        )
        out.append(f"  adapter         {batching}")
    out.append(f"  recommended     timeout {f['recommended_timeout']:g} s")
    if "recommended_framing" in f:
        out.append(f"                  framing: {f['recommended_framing']}")
    return out


# -- HTML ----------------------------------------------------------------------------------


def plotting_available() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _svg(fig: Any) -> str:
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    return text[text.index("<svg") :]


def _histogram(latencies: dict[str, list[float]], title: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.5))
    for name, values in latencies.items():
        ax.hist([v * 1e3 for v in values], bins=50, alpha=0.6, label=name)
    ax.set_xlabel("transaction latency (ms)")
    ax.set_ylabel("transactions")
    ax.set_title(title)
    ax.legend()
    svg = _svg(fig)
    plt.close(fig)
    return svg


def _timeline(line: LineReport) -> str:
    """One transaction (the median round trip's) on a time axis from its start."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    samples = sorted(line.samples, key=lambda s: s.last - s.start)
    s = samples[len(samples) // 2]
    assert line.request_wire is not None and line.answer_wire is not None
    ms = 1e3
    bars = [
        ("request on the wire", 0.0, line.request_wire),
        ("port says sent", 0.0, s.sent - s.start),
        ("wait for the answer", s.sent - s.start, s.first - s.sent),
        ("answer read", s.first - s.start, max(s.last - s.first, 1e-6)),
        ("answer on the wire (length)", s.last - s.start - line.answer_wire, line.answer_wire),
    ]
    fig, ax = plt.subplots(figsize=(8, 2.8))
    for i, (_what, start, width) in enumerate(bars):
        ax.barh(i, width * ms, left=start * ms)
        ax.text((start + width) * ms, i, f" {width * ms:.3f} ms", va="center", fontsize=8)
    ax.set_yticks(range(len(bars)), [b[0] for b in bars])
    ax.invert_yaxis()
    ax.set_xlabel("ms from the request handed to the port")
    ax.set_title(f"one transaction (the median of {len(samples)}) on {line.port}")
    svg = _svg(fig)
    plt.close(fig)
    return svg


def as_html(suite: SuiteResult | None, line: LineReport | None) -> str:
    """The whole report, one file: the table, then the plots (inline SVG)."""
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>pyrtu bench</title>",
        "<style>body{font-family:sans-serif;max-width:60em;margin:2em auto}"
        "pre{background:#f4f4f4;padding:1em;overflow-x:auto}</style></head><body>",
        "<h1>pyrtu bench</h1>",
        f"<pre>{html.escape(table(suite, line))}</pre>",
    ]
    if suite is not None and suite.latencies:
        parts.append("<h2>Latency of a master's transactions on the virtual bus</h2>")
        parts.append(_histogram(suite.latencies, "read of 10 registers, virtual bus"))
    if suite is not None and suite.vbus_line is not None and suite.vbus_line.samples:
        parts.append("<h2>One transaction on the virtual bus</h2>")
        parts.append(_timeline(suite.vbus_line))
    if line is not None and line.round_trips:
        parts.append(f"<h2>Your line: {html.escape(line.port)}</h2>")
        parts.append(_histogram({line.port: line.round_trips}, "round trips"))
        if line.samples:
            parts.append(_timeline(line))
    parts.append("</body></html>")
    return "\n".join(parts)


__all__ = ["as_html", "as_json", "human", "machine", "plotting_available", "table"]
