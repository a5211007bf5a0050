"""The sync Master against the libmodbus client, back to back on one pty pair.

    python bench/investigations/pty_vs_libmodbus.py [N] [--rounds R]

A socat pty pair, the libmodbus server (tests/peers) on one side; on the other, N FC 03
reads of 10 registers by `pyrtu.Master` (``t35=0``: no wire), then N by the libmodbus
client's bench mode, R times.  Prints each round's rates, the ratio, and the CPU per
transaction of each client (the Master's thread time; the client process's user +
system).  Run it from another checkout's root (``PYTHONPATH=<checkout>``) to compare.

``--floor`` adds, in each round, the least a Python driver can do per transaction:
``os.write`` of the prebuilt request, ``poll``/``os.read`` until the 25 bytes are in,
the CRC check and the unpacking of the 10 registers, and nothing else (no framing,
no checks of the answer's header, no timeout policy).  Its ratio to the libmodbus
client bounds what any master written in Python reaches on this pty and machine.
The round's figures end with the medians over the rounds.
"""

from __future__ import annotations

import argparse
import inspect
import os
import select
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

import serial  # noqa: E402
from peers.tools import (  # type: ignore[import-not-found]  # noqa: E402
    build_peers,
    libmodbus_bench,
    libmodbus_server,
    socat_pair,
)

from pyrtu import crc16  # noqa: E402
from pyrtu.drivers.master import Master  # noqa: E402

REQUEST = bytes.fromhex("01030000000ac5cd")  # FC 03, slave 1, 10 registers from 0
ANSWER = 25


def timed(n: int, one: object) -> tuple[float, float]:
    """(transactions/s, thread CPU µs per transaction) of ``n`` calls of ``one``."""
    assert callable(one)
    for _ in range(200):
        one()
    c0, w0 = time.thread_time(), time.perf_counter()
    for _ in range(n):
        one()
    wall, cpu = time.perf_counter() - w0, time.thread_time() - c0
    return n / wall, cpu / n * 1e6


def master_round(path: str, n: int) -> tuple[float, float]:
    kw = {"exclusive": False} if "exclusive" in inspect.signature(Master).parameters else {}
    m = Master(path, 115200, parity="N", timeout=1.0, t35=0, **kw)
    try:
        return timed(n, lambda: m.read_holding_registers(1, 0, 10))
    finally:
        m.close()


def floor_round(path: str, n: int) -> tuple[float, float]:
    """The least a Python driver does per transaction (see the module's text)."""
    port = serial.Serial(path, 115200, timeout=1.0)
    fd = port.fileno()
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    words = struct.Struct(">10H").unpack_from

    def one() -> tuple[int, ...]:
        os.write(fd, REQUEST)
        answer = b""
        while len(answer) < ANSWER:
            if not poller.poll(1000):
                raise TimeoutError("the libmodbus server did not answer within 1 s")
            answer += os.read(fd, 4096)
        if crc16(answer) != 0:
            raise ValueError(f"bad CRC in {answer.hex()}")
        return words(answer, 3)

    try:
        return timed(n, one)
    finally:
        port.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("n", type=int, nargs="?", default=6000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--floor", action="store_true", help="add the minimal Python loop")
    args = ap.parse_args()
    peers = build_peers(Path(tempfile.mkdtemp(prefix="pyrtu-peers-")))
    ratios: dict[str, list[float]] = {"pyrtu": [], "floor": []}
    with socat_pair() as (a, b), libmodbus_server(peers, b, 1):
        for _ in range(args.rounds):
            tps, cpu = master_round(a, args.n)
            floor = floor_round(a, args.n) if args.floor else None
            lm = libmodbus_bench(peers, a, 1, args.n, address=0, warmup=10)
            ratios["pyrtu"].append(tps / lm["tps"])
            text = f"pyrtu {tps:,.0f}/s {cpu:.1f} us/tx; "
            if floor is not None:
                ratios["floor"].append(floor[0] / lm["tps"])
                text += f"floor {floor[0]:,.0f}/s {floor[1]:.1f} us/tx; "
            print(
                text + f"libmodbus {lm['tps']:,.0f}/s {lm['cpu_us_per_tx']:.1f} us/tx; "
                f"ratio {tps / lm['tps']:.2f}"
                + (f", floor {floor[0] / lm['tps']:.2f}" if floor is not None else ""),
                flush=True,
            )
    print(
        "median ratio to the libmodbus client: pyrtu "
        f"{statistics.median(ratios['pyrtu']):.2f}"
        + (f", floor {statistics.median(ratios['floor']):.2f}" if ratios["floor"] else "")
    )


if __name__ == "__main__":
    main()
