"""A pyrtu Slave in its own process, serving the pattern of `pattern.py`.

    python tests/peers/pyrtu_slave.py PORT ADDRESS[,ADDRESS...] [--baud N] [--t35 S]

Opens PORT as 8N1 (pseudo-terminals refuse parity).  ``--t35 0`` turns the
inter-frame wait off (a pseudo-terminal pair has no wire timing); without it the
slave uses the specification's timing for the baud rate.  Prints
``READY <port> <addresses>`` once serving, and on SIGTERM/SIGINT stops, prints
``STATS {counters as JSON}`` and exits 0.  Needs pyrtu importable (PYTHONPATH).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import pattern

from pyrtu.drivers.slave import Slave


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("port")
    parser.add_argument("addresses", help="slave address, or several separated by commas")
    parser.add_argument("--baud", type=int, default=115200)
    parser.add_argument("--t35", type=float, default=None, help="seconds (0: no wait)")
    args = parser.parse_args(argv)
    addresses = {int(a) for a in args.addresses.split(",")}
    address: int | set[int] = next(iter(addresses)) if len(addresses) == 1 else addresses
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda _signum, _frame: stop.set())
    slave = Slave(
        args.port,
        address=address,
        store=pattern.pattern_store(min(addresses)),  # one store: the lowest address's pattern
        baudrate=args.baud,
        parity="N",
        stopbits=1,
        bytesize=8,
        t35=args.t35,
    )
    slave.start()
    print(f"READY {args.port} {args.addresses}", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        slave.stop()
    print("STATS " + json.dumps(dict(slave.counters), default=str), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
