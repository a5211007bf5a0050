"""Where a polled bus's wire time goes (issue 18, target (b)): the 4-bus run of
bench_client.py (``--loops --buses 4 --drive cv100``) with the masters' protocol
events timed.

    python bench/investigations/bus_timeline.py [--loop pyrtu|asyncio|uvloop]
        [--seconds S] [--buses N]

Every `ClientProtocol.transmitted` and ``wait_done`` of the masters is recorded (the
methods are wrapped for the run: the masters are bench_client.eight_buses's own), and
per transaction: the master's silence before its request (from the read that
completed the previous answer to the write; t3.5 = 1750 µs at 115200 is the least)
and the answer's delay (from the end of the request's write to the read that
completed the answer), split by the number of reads the answer took.  An answer read
in two or more reads had its last byte read as it came (a wait for input), so its
delay is the bus's and the slave's: request on the wire (8 characters), t3.5, the
slave's turnaround, the answer on the wire (19 characters), i.e. 4094 µs plus
what the slave and the hubs add.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # bench/

import bench_client

from pyrtu.protocol.client import ClientProtocol

ANSWER = 5 + 2 * 7  # FC 03 x 7 registers


def _record(events: dict[int, list[tuple[str, float, float]]]) -> None:
    """Wrap the protocol's inputs to append (kind, a, b) per protocol."""
    transmitted, wait_done = ClientProtocol.transmitted, ClientProtocol.wait_done

    def tx(self: ClientProtocol, end: float, start: float | None = None) -> None:
        events[id(self)].append(("tx", end if start is None else start, end))
        transmitted(self, end, start)

    def rd(self: ClientProtocol, data: bytes, now: float) -> None:
        events[id(self)].append(("rd", float(len(data)), now))
        wait_done(self, data, now)

    ClientProtocol.transmitted = tx  # type: ignore[method-assign]
    ClientProtocol.wait_done = rd  # type: ignore[method-assign]


def _timeline(events: dict[int, list[tuple[str, float, float]]]) -> dict[str, list[float]]:
    """µs per transaction: "silence" and "answer N reads" (see the module docstring)."""
    out: dict[str, list[float]] = collections.defaultdict(list)
    for evs in events.values():
        last_rx = tx_end = None
        got = reads = 0
        for kind, a, b in evs:
            if kind == "tx":
                if last_rx is not None:
                    out["silence"].append((a - last_rx) * 1e6)
                tx_end, got, reads = b, 0, 0
            elif a and tx_end is not None:
                got, reads = got + int(a), reads + 1
                if got >= ANSWER:
                    out[f"answer, {min(reads, 3)}{'+' if reads >= 3 else ''} reads"].append(
                        (b - tx_end) * 1e6
                    )
                    last_rx, tx_end = b, None
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--loop", choices=sorted(bench_client.EVENT_LOOPS), default="pyrtu")
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--buses", type=int, default=4)
    args = ap.parse_args()
    events: dict[int, list[Any]] = collections.defaultdict(list)
    _record(events)
    e = bench_client.eight_buses(115200, args.seconds, args.buses, "cv100", event_loop=args.loop)
    print(f"{args.loop}: ratios {' '.join(f'{r:.3f}' for r in e['ratios'])}", end="")
    print(f", master CPU {e['cpu_us_per_tx']:.0f} µs/tx")
    print("| µs per transaction | count | p10 | median | p90 |")
    print("|---|---:|---:|---:|---:|")
    for name, values in sorted(_timeline(events).items()):
        v = sorted(values)
        p = [v[int(len(v) * q)] for q in (0.1, 0.5, 0.9)]
        print(f"| {name} | {len(v)} | {p[0]:.0f} | {p[1]:.0f} | {p[2]:.0f} |")


if __name__ == "__main__":
    main()
