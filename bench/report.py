"""Run the core benchmarks once and write their medians and ratios to bench/RESULTS.md.

    python bench/report.py            # (make bench)

Every figure in the generated section comes from the one pytest-benchmark run this
script starts, so ratios compare numbers measured side by side on the same (shared,
noisy) machine.  Other sections of RESULTS.md (outside the markers) are kept.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "RESULTS.md"
BEGIN, END = "<!-- core:begin (bench/report.py) -->", "<!-- core:end -->"


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def run_benchmarks(out: Path) -> list[dict[str, Any]]:
    cmd = [
        sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
        str(HERE / "bench_crc.py"), str(HERE / "bench_core.py"),
        f"--benchmark-json={out}", "--benchmark-min-time=0.05", "--benchmark-max-time=1.0",
    ]  # fmt: skip
    subprocess.run(cmd, check=True)
    return list(json.loads(out.read_text())["benchmarks"])


def _fmt_time(s: float) -> str:
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6)):
        if s >= scale:
            return f"{s / scale:.3g} {unit}"
    return f"{s / 1e-9:.3g} ns"


def _fmt_rate(bytes_per_s: float) -> str:
    if bytes_per_s >= 1e9:
        return f"{bytes_per_s / 1e9:.3g} GB/s"
    return f"{bytes_per_s / 1e6:.3g} MB/s"


def render(benches: list[dict[str, Any]]) -> str:
    by_group: dict[str, list[dict[str, Any]]] = {}
    for b in benches:
        by_group.setdefault(b["group"] or "", []).append(b)

    def median(group: str, name_part: str) -> float:
        for b in by_group.get(group, []):
            if b["name"] == name_part or b["name"] == f"{name_part}[{group.split(' ', 1)[1]}]":
                return float(b["stats"]["median"])
        raise KeyError(f"{group}: {name_part}")

    lines = [
        BEGIN,
        "## Core (issue 2)",
        "",
        f"Measured {time.strftime('%Y-%m-%d')} on {_cpu()}, Python {platform.python_version()},"
        " in one run of `python bench/report.py` (pytest-benchmark medians; the machine is"
        " shared, so compare ratios within this run).",
        "",
    ]
    for group in sorted(by_group):
        rows = sorted(by_group[group], key=lambda b: b["stats"]["median"])
        fastest = rows[0]["stats"]["median"]
        lines += [
            f"### {group}",
            "",
            "| benchmark | median | throughput | x fastest |",
            "|---|---|---|---|",
        ]
        for b in rows:
            med = float(b["stats"]["median"])
            size = b.get("extra_info", {}).get("bytes")
            rate = _fmt_rate(size / med) if size and "noop" not in b["name"] else ""
            lines.append(f"| `{b['name']}` | {_fmt_time(med)} | {rate} | {med / fastest:.2f} |")
        lines.append("")

    # The targets, from the same run.
    targets = []
    try:
        crc8 = median("crc16 8 B", "test_c_crc16")
        noop = median("crc16 8 B", "test_c_noop")
        noop_args = median("crc16 8 B", "test_c_noop_same_arguments")
        targets.append(
            f"| `crc16` at 8 B within 1.3x of an empty cffi call | {_fmt_time(crc8)} vs "
            f"{_fmt_time(noop_args)} for an empty call with the same arguments: "
            f"**{crc8 / noop_args:.2f}x**; vs an empty call with no arguments "
            f"({_fmt_time(noop)}): {crc8 / noop:.2f}x |"
        )
        mib = 1 << 20
        big = median("crc16 1 MiB", "test_c_crc16")
        clmul = median("crc16 1 MiB", "test_c_path[1 MiB-clmul]")
        vclmul = median("crc16 1 MiB", "test_c_path[1 MiB-vclmul]")
        twin = median("crc16 1 MiB", "test_python_twin")
        targets.append(
            f"| `crc16` at 1 MiB >= 10 GB/s with PCLMULQDQ | `crc16` {_fmt_rate(mib / big)}; "
            f"clmul path {_fmt_rate(mib / clmul)}; vclmul path {_fmt_rate(mib / vclmul)}; "
            f"pure-Python twin {_fmt_rate(mib / twin)} ({twin / big:.0f}x slower) |"
        )
    except KeyError as exc:
        targets.append(f"| crc16 | missing benchmark {exc} |")
    try:
        group = "parse_stream 10 MB"
        c = median(group, "test_parse_stream[c]")
        py = median(group, "test_parse_stream[python]")
        targets.append(
            f"| `parse_stream` >= 150 MB/s and >= 50x the twin | C {_fmt_rate(10e6 / c)}, "
            f"twin {_fmt_rate(10e6 / py)}: **{py / c:.0f}x** |"
        )
    except KeyError as exc:
        targets.append(f"| parse_stream | missing benchmark {exc} |")
    lines += ["### Targets (issue 2)", "", "| target | measured |", "|---|---|", *targets, "", END]
    return "\n".join(lines)


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        benches = run_benchmarks(Path(tmp) / "bench.json")
    section = render(benches)
    old = RESULTS.read_text() if RESULTS.exists() else "# Benchmark results\n\n"
    if BEGIN in old and END in old:
        new = old[: old.index(BEGIN)] + section + old[old.index(END) + len(END) :]
    else:
        new = old.rstrip() + "\n\n" + section + "\n"
    RESULTS.write_text(new)
    print(section)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
