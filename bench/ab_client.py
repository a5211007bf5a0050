"""Before/after CPU per transaction of the masters, each in a fresh process.

    python bench/ab_client.py BEFORE_DIR [--rounds N]

bench_client.py measures the master of this tree inside its own process (pymodbus
imported, buses and loops already made) and the tree before in a fresh one; this
runs both trees' `Master` and `AsyncMaster` (on `pyrtu.drivers.aio.run`) the same way, a
fresh interpreter each, interleaved with the libmodbus client on the same bus and
slave (bench_client.py's buses, slave and programs): medians of the rounds.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_client as B

ROOT = str(Path(__file__).resolve().parent.parent)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("before")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--bauds", type=int, nargs="+", default=[9600, 115200])
    args = ap.parse_args()
    peers = B.build_peers(Path(tempfile.mkdtemp(prefix="pyrtu-peers-")))
    programs = {"Master": B._BASELINE, "AsyncMaster": B._BASELINE_ASYNC}
    print("| baud | master | before µs/tx | now µs/tx | now / before | now / libmodbus |")
    print("|---:|---|---:|---:|---:|---:|")
    for baud in args.bauds:
        n = 40 if baud < 19200 else 300
        runs: dict[str, list[float]] = {}
        with B.vbus(baud) as (paths, _hub), B.slave(paths[1], baud):
            for i in range(args.rounds):
                trees = [(args.before, "before"), (ROOT, "now")]
                for name, program in programs.items():
                    for tree, label in trees[:: 1 if i % 2 else -1]:  # either first in turn
                        r = B.baseline_master(tree, paths[0], baud, n, program)
                        runs.setdefault(f"{name} {label}", []).append(r["cpu_us"])
                lm = B.libmodbus_master(peers, paths[0], baud, n)
                runs.setdefault("libmodbus", []).append(lm["cpu_us"])
        med = {k: statistics.median(v) for k, v in runs.items()}
        for name in programs:
            b, a = med[f"{name} before"], med[f"{name} now"]
            print(
                f"| {baud} | {name} | {b:.0f} | {a:.0f} | {a / b:.2f}x | "
                f"{a / med['libmodbus']:.2f}x (libmodbus {med['libmodbus']:.0f}) |",
                flush=True,
            )


if __name__ == "__main__":
    main()
