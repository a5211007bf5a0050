"""The silences on the wire of the 4-bus run (bench_client.py ``--loops``), from the
hubs' own captures: per bus, the slave's turnaround (the end of a request on the
wire to the start of its answer) and the master's (the end of an answer to the next
request), against t3.5 = 1750 µs at 115200 baud.  What a bus loses to the wire
limit is their excess over t3.5.

    python bench/investigations/wire_gaps.py [--loop pyrtu|asyncio|uvloop] [--buses N] [--seconds S]
                              [--drive cv100|floor]

Each hub writes a capture (``pyrtu vbus --capture``: its hub then runs the Python
loop, the C loop has no capture, so the ratios are a little below bench_client's);
a run of back-to-back bytes ends at its last byte's time and began one character
per byte before.  Requests are 8 bytes (FC 03), answers 19.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import statistics
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # bench/

import bench_client

from pyrtu.core.line import LineConfig
from pyrtu.vbus import read_capture

REQUEST = 8


def turnarounds(path: str, char: float) -> tuple[list[float], list[float]]:
    """(slave, master) turnarounds in µs from one capture."""
    data, chunks = read_capture(path)
    runs = []
    for i, (off, t) in enumerate(chunks):
        end = chunks[i + 1][0] if i + 1 < len(chunks) else len(data)
        runs.append((end - off, t))
    slave: list[float] = []
    master: list[float] = []
    for (n0, t0), (n1, t1) in itertools.pairwise(runs):
        gap = (t1 - n1 * char - t0) * 1e6
        (slave if n0 == REQUEST else master).append(gap)
    return slave, master


def quantiles(v: list[float]) -> str:
    if len(v) < 10:
        return "-"
    q = statistics.quantiles(v, n=10)
    return f"{q[0]:.0f} / {statistics.median(v):.0f} / {q[8]:.0f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--loop", choices=sorted(bench_client.EVENT_LOOPS), default="asyncio")
    ap.add_argument("--buses", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--drive", choices=("cv100", "floor"), default="cv100")
    args = ap.parse_args()
    captures: list[str] = []
    plain = bench_client.process

    @contextlib.contextmanager
    def with_capture(argv: list[str], *rest: Any) -> Iterator[Any]:
        if "vbus" in argv:
            path = str(Path(tempfile.mkdtemp(prefix="pyrtu-gaps-")) / "bus.cap")
            captures.append(path)
            argv = [*argv, "--capture", path]
        with plain(argv, *rest) as out:
            yield out

    bench_client.process = with_capture  # type: ignore[assignment]
    e = bench_client.eight_buses(115200, args.seconds, args.buses, args.drive, event_loop=args.loop)
    char = LineConfig(baudrate=115200, parity="N").char_time
    print(f"{args.loop}, {args.buses} buses, {args.drive}: ratios "
          + " ".join(f"{r:.3f}" for r in e["ratios"]))  # fmt: skip
    print(
        "| bus | slave turnaround p10 / median / p90 µs | master turnaround p10 / median / p90 µs |"
    )
    print("|---:|---:|---:|")
    for i, path in enumerate(captures):
        slave, master = turnarounds(path, char)
        print(f"| {i} | {quantiles(slave)} | {quantiles(master)} |")


if __name__ == "__main__":
    main()
