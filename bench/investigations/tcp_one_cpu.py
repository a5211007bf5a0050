"""The Modbus TCP benchmarks with every process on one CPU, beside the usual run.

    python bench/investigations/tcp_one_cpu.py [--cpu 1] [--runs 1]

bench/bench_tcp_master.py, bench_tcp_async.py and bench_tcp_server.py measure a
client's (or server's) CPU per transaction against a peer in another process on
127.0.0.1.  On this project's 2-vCPU VM the figure depends on where the peer
runs: with the two processes free to run on either CPU, each request or answer
usually finds the other process asleep on the other, idle CPU, and waking it is
charged to the sender's system time; pinned to one CPU (the benchmark and every
process it starts inherit the affinity: `os.sched_setaffinity` before the
``pytest`` process is made) the wake-up is a local one.  This runs each
benchmark both ways, one after the other (``--runs`` times), and prints each
row's median CPU per transaction and its ratios to the libmodbus and pymodbus
rows of the same run: what of a target's ratio is the clients' own work and what
is the machine's.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BENCHES = ("bench_tcp_master.py", "bench_tcp_async.py", "bench_tcp_server.py")


def run(bench: str, cpu: int | None) -> dict[str, float]:
    """One run of ``bench`` (``cpu``: pinned to it): each row's median CPU µs per
    transaction."""
    with tempfile.TemporaryDirectory(prefix="pyrtu-one-cpu-") as tmp:
        out = Path(tmp) / "out.json"
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
               str(ROOT / "bench" / bench), "--benchmark-min-time=0.05",
               "--benchmark-max-time=1.0", f"--benchmark-json={out}"]  # fmt: skip

        def pin() -> None:
            if cpu is not None:
                os.sched_setaffinity(0, {cpu})

        subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, preexec_fn=pin)
        doc = json.loads(out.read_text())
    return {
        b["name"]: statistics.median(b["extra_info"]["cpu_us_per_tx"]) for b in doc["benchmarks"]
    }


def ratio(rows: dict[str, float], name: str, key: str) -> str:
    base = next((v for k, v in rows.items() if key in k), None)
    return f"{rows[name] / base:.2f}" if base else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--cpu", type=int, default=1, help="the CPU of the pinned runs")
    ap.add_argument("--runs", type=int, default=1, help="each way, one after the other")
    args = ap.parse_args()
    if args.cpu not in os.sched_getaffinity(0):
        ap.error(f"--cpu: this process may not run on CPU {args.cpu}")
    for bench in BENCHES:
        for n in range(args.runs):
            for cpu in (None, args.cpu):
                rows = run(bench, cpu)
                where = "any CPU" if cpu is None else f"CPU {cpu} only"
                print(f"{bench} ({where}, run {n + 1})")
                for name, us in rows.items():
                    print(f"  {name:45} {us:7.1f} µs   x libmodbus "
                          f"{ratio(rows, name, 'libmodbus')}   x pymodbus "
                          f"{ratio(rows, name, 'pymodbus')}")  # fmt: skip
                sys.stdout.flush()


if __name__ == "__main__":
    main()
