"""Run bench/bench_serial.py once: pytest-benchmark's JSON (``--json``) and a summary
on stdout.  bench/report.py runs it for bench/RESULTS.md.

    python bench/run_serial.py [--json FILE] [pytest args...]

``--from-json FILE`` prints the summary of an earlier run without measuring.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from importlib import metadata
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
HEADING = "## Master/slave over serial (issue 4)"
TARGET_LIBMODBUS = 0.8
TARGET_PYMODBUS = 10.0


def run_benchmark(json_path: Path, extra: list[str]) -> None:
    cmd = [
        sys.executable,
        "-m",
        "pytest",
        str(BENCH / "bench_serial.py"),
        "-p",
        "no:cacheprovider",
        "-q",
        f"--benchmark-json={json_path}",
        "--benchmark-columns=median,rounds",
        *extra,
    ]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    subprocess.run(cmd, check=True, cwd=ROOT, env=env)


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def libmodbus_version() -> str:
    done = subprocess.run(
        ["pkg-config", "--modversion", "libmodbus"], capture_output=True, text=True, check=False
    )
    return done.stdout.strip() or "unknown"


def fmt_int(x: float) -> str:
    return f"{x:,.0f}"


def fmt_us(x: float | None) -> str:
    return "n/a" if x is None else f"{x:,.1f}"


def split_rows(
    data: dict[str, Any],
) -> tuple[dict[tuple[str, str], dict[str, Any]], list[dict[str, Any]]]:
    """The pty figures by (client, server) and the virtual bus's, from the JSON."""
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    vbus: list[dict[str, Any]] = []
    for bench in data["benchmarks"]:
        info = bench["extra_info"]
        if info.get("path") == "socat pty pair":
            for client, numbers in info["clients"].items():
                rows[(client, info["server"])] = numbers
        elif "baudrate" in info:
            vbus.append(info)
    return rows, vbus


def section(data: dict[str, Any]) -> str:
    rows, vbus = split_rows(data)
    cycles = next(iter(rows.values()))["rounds"] if rows else 0
    machine = data.get("machine_info", {})
    import pyrtu

    lines = [
        HEADING,
        "",
        "`python bench/run_serial.py` (bench/bench_serial.py, pytest-benchmark), one run, "
        f"{data.get('datetime', '')[:19]} UTC.  {cpu_model()}, {os.cpu_count()} cores, "
        f"Python {machine.get('python_version', platform.python_version())}, pyrtu backend "
        f"`{pyrtu.BACKEND}`, pymodbus {version('pymodbus')}, minimalmodbus "
        f"{version('minimalmodbus')}, pyserial {version('pyserial')}, libmodbus "
        f"{libmodbus_version()}.",
        "",
        "FC 03, 10 holding registers, one transaction at a time, every answer checked.  "
        "Medians of the rounds; CPU time per transaction of the client (its thread, or "
        "the libmodbus client's process) and of the server process.",
        "",
        "### Pseudo-terminal pair (socat `pty,raw,echo=0`; pyrtu `t35=0` on both sides)",
        "",
        "Per server, the clients take turns: a cycle is one round of each (0.1-0.5 s), "
        f"{cycles} cycles.  *vs libmodbus client* is the median over the cycles of the "
        "client's rate divided by the libmodbus client's rate in the same cycle: the "
        "machine is shared and drifts (rounds of one pair vary by tens of percent), so "
        "compare those ratios rather than transactions/s across servers.",
        "",
        "| client | server | transactions/s | vs libmodbus client | client CPU µs/tx | "
        "server CPU µs/tx |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for (client, server), info in rows.items():
        lines.append(
            f"| {client} | {server} | {fmt_int(info['tps'])} | "
            f"{info['vs_libmodbus_client']:.2f} | "
            f"{fmt_us(info['client_cpu_us_per_tx'])} | {fmt_us(info['server_cpu_us_per_tx'])} |"
        )

    def rel(client: str, server: str) -> float | None:
        info = rows.get((client, server))
        return None if info is None else float(info["vs_libmodbus_client"])

    def tps(client: str, server: str) -> float | None:
        info = rows.get((client, server))
        return None if info is None else float(info["tps"])

    anchor = rows.get(("libmodbus", "libmodbus"))
    if anchor is not None and "tps_min" in anchor:
        lines += [
            "",
            f"The anchor, libmodbus client against libmodbus server: {fmt_int(anchor['tps'])}/s "
            f"(rounds from {fmt_int(anchor['tps_min'])} to {fmt_int(anchor['tps_max'])}/s; "
            "the issue quotes about 14,600/s through socat on this kind of machine).",
        ]
    lines += ["", "Ratios (same run, from the per-cycle ratios):", ""]
    ours = rel("pyrtu", "libmodbus")
    if ours:
        verdict = "met" if ours >= TARGET_LIBMODBUS else "NOT met"
        lines.append(
            f"- pyrtu master / libmodbus client, both against the libmodbus server: "
            f"**{ours:.2f}x** (target >= {TARGET_LIBMODBUS}x: {verdict})"
        )
    for server in ("libmodbus", "pyrtu"):
        ours = rel("pyrtu", server)
        for other in ("pymodbus", "minimalmodbus"):
            theirs = rel(other, server)
            if ours and theirs:
                extra = ""
                if other == "pymodbus":
                    ok = ours / theirs >= TARGET_PYMODBUS
                    extra = f" (target >= {TARGET_PYMODBUS:.0f}x: {'met' if ok else 'NOT met'})"
                lines.append(
                    f"- pyrtu master / {other}, against the {server} server: "
                    f"**{ours / theirs:.1f}x**{extra}"
                )
    for server in ("libmodbus", "pyrtu"):
        c, py = rel("pyrtu", server), rel("pyrtu-python", server)
        if c and py:
            lines.append(
                f"- pyrtu master, C framer / pure-Python framer, against the {server} server: "
                f"{c / py:.2f}x"
            )
    ps, ls = tps("libmodbus", "pyrtu"), tps("libmodbus", "libmodbus")
    if ps and ls:
        lines.append(
            f"- pyrtu slave / libmodbus server, both polled by the libmodbus client: "
            f"{ps / ls:.2f}x (not interleaved: two tests)"
        )
    lines += [
        "",
        "### Virtual bus, specification timing (pyrtu master and pyrtu slave, 8N1)",
        "",
        "Wire limit = 1 / (33 character times + 2 x t3.5): an 8-byte request and a 25-byte "
        "response, each after the inter-frame silence (t3.5 = 3.5 characters up to 19200 "
        "baud, 1750 µs above).",
        "",
        "| baud | character µs | t3.5 µs | transactions/s | wire limit /s | ratio | "
        "master CPU µs/tx | slave CPU µs/tx |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for info in sorted(vbus, key=lambda i: int(i["baudrate"])):
        lines.append(
            f"| {info['baudrate']} | {info['char_time_us']:.1f} | {info['t35_us']:.0f} | "
            f"{info['tps']:.1f} | {info['wire_limit_tps']:.1f} | **{info['ratio_to_wire']:.3f}** | "
            f"{fmt_us(info['client_cpu_us_per_tx'])} | {fmt_us(info['server_cpu_us_per_tx'])} |"
        )
    lines += [
        "",
        "Server CPU comes from /proc (10 ms ticks) over all rounds; the virtual bus's hub "
        "runs in the benchmark process (its CPU is in neither column).",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--json", type=Path, help="keep pytest-benchmark's JSON here")
    parser.add_argument("--from-json", type=Path, help="summarise this JSON only")
    parser.add_argument(
        "--no-write",
        action="store_true",
        help="accepted and ignored: RESULTS.md is written by bench/report.py only",
    )
    args, extra = parser.parse_known_args(argv)
    sys.path.insert(0, str(ROOT))
    if args.from_json:
        json_path = args.from_json
    else:
        json_path = args.json or Path(tempfile.mkdtemp(prefix="pyrtu-bench-")) / "serial.json"
        run_benchmark(json_path, extra)
    data = json.loads(json_path.read_text(encoding="utf-8"))
    text = section(data)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
