"""The sync Master against the libmodbus client, back to back on one pty pair.

    python bench/pty_vs_libmodbus.py [N] [--rounds R]

A socat pty pair, the libmodbus server (tests/peers) on one side; on the other, N FC 03
reads of 10 registers by `pyrtu.Master` (``t35=0``: no wire), then N by the libmodbus
client's bench mode, R times.  Prints each round's rates, the ratio, and the CPU per
transaction of each client (the Master's thread time; the client process's user +
system).  Run it from another checkout's root (``PYTHONPATH=<checkout>``) to compare.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from peers.tools import (  # type: ignore[import-not-found]  # noqa: E402
    build_peers,
    libmodbus_bench,
    libmodbus_server,
    socat_pair,
)

from pyrtu.master import Master  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("n", type=int, nargs="?", default=6000)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    peers = build_peers(Path(tempfile.mkdtemp(prefix="pyrtu-peers-")))
    kw = {"exclusive": False} if "exclusive" in inspect.signature(Master).parameters else {}
    with socat_pair() as (a, b), libmodbus_server(peers, b, 1):
        for _ in range(args.rounds):
            m = Master(a, 115200, parity="N", timeout=1.0, t35=0, **kw)
            try:
                for _ in range(200):
                    m.read_holding_registers(1, 0, 10)
                c0, w0 = time.thread_time(), time.perf_counter()
                for _ in range(args.n):
                    m.read_holding_registers(1, 0, 10)
                wall, cpu = time.perf_counter() - w0, time.thread_time() - c0
            finally:
                m.close()
            lm = libmodbus_bench(peers, a, 1, args.n, address=0, warmup=10)
            tps = args.n / wall
            print(
                f"pyrtu {tps:,.0f}/s {cpu / args.n * 1e6:.1f} us/tx; libmodbus {lm['tps']:,.0f}/s "
                f"{lm['cpu_us_per_tx']:.1f} us/tx; ratio {tps / lm['tps']:.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
