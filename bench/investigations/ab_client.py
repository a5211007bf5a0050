"""Before/after CPU per transaction of the masters, each in a fresh process.

    python bench/investigations/ab_client.py BEFORE_DIR [--rounds N]

bench_client.py measures the master of this tree inside its own process (pymodbus
imported, buses and loops already made) and the tree before in a fresh one; this
runs both trees' `Master` and `AsyncMaster` (on `pyrtu.drivers.aio.run`) the same way, a
fresh interpreter each, interleaved with the libmodbus client on the same bus and
slave (bench_client.py's buses, slave and programs): medians of the rounds.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # bench/

import bench_client

ROOT = str(Path(__file__).resolve().parents[2])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("before")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--bauds", type=int, nargs="+", default=[9600, 115200])
    args = ap.parse_args()
    programs = {"Master": bench_client._BASELINE, "AsyncMaster": bench_client._BASELINE_ASYNC}

    def one_round(i: int, path: str, baud: int, n: int) -> Iterator[tuple[str, float]]:
        trees = [(args.before, "before"), (ROOT, "now")]
        for name, program in programs.items():
            for tree, label in trees[:: 1 if i % 2 else -1]:  # either first in turn
                yield (
                    f"{name} {label}",
                    bench_client.baseline_master(tree, path, baud, n, program)["cpu_us"],
                )

    print("| baud | master | before µs/tx | now µs/tx | now / before | now / libmodbus |")
    print("|---:|---|---:|---:|---:|---:|")
    for baud, med in bench_client.cpu_rounds(args.bauds, args.rounds, one_round):
        for name in programs:
            b, a = med[f"{name} before"], med[f"{name} now"]
            print(
                f"| {baud} | {name} | {b:.0f} | {a:.0f} | {a / b:.2f}x | "
                f"{a / med['libmodbus']:.2f}x (libmodbus {med['libmodbus']:.0f}) |",
                flush=True,
            )


if __name__ == "__main__":
    main()
