"""Virtual bus delivery timing, apart from what the kernel adds: figures over many runs.

    .venv/bin/python bench/vbus_timing.py [runs]      # default 20 runs per baud rate

Each run is one measurement of tests/vbus/test_vbus_timing.py (the same code): the bare
pty latency of this machine (one-byte writes 1 ms apart, the same reader process),
then a 256-byte 8E1 frame written to drop0 in one call and read on drop1.  Prints,
per baud rate, the median over the runs of each figure, and how many runs met every
bound of the test.  Nothing is asserted: the test does that.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests" / "vbus"))

from test_vbus_timing import Run, measure

FIGURES = [
    ("pty_p50_us", "bare pty p50"),
    ("pty_p99_us", "bare pty p99"),
    ("pty_cold_p50_us", "bare pty p50 after 20 ms idle"),
    ("spacing_abs_err_median_us", "spacing |err| median"),
    ("spacing_abs_err_p99_us", "spacing |err| p99"),
    ("spacing_abs_err_max_us", "spacing |err| max"),
    ("span_err_us", "first-to-last span err"),
    ("raw_offset_us", "end-to-end offset, raw"),
    ("own_offset_us", "end-to-end offset - 2 x pty p50"),
]
SIGNED = {"span_err_us", "raw_offset_us", "own_offset_us"}


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("runs", nargs="?", type=int, default=20, help="runs per baud rate")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    runs = args.runs
    print(f"load average before: {os.getloadavg()}")
    print("| figure (median over runs, us) | 9600 8E1 | 115200 8E1 |")
    print("|---|---|---|")
    results: dict[int, list[Run]] = {}
    for baud in (9600, 115200):
        results[baud] = [measure(baud, "E", 1, [(256, 0)]) for _ in range(runs)]
    for key, label in FIGURES:
        cells = [statistics.median(r.figures()[key] for r in results[b]) for b in results]
        fmt = "+.0f" if key in SIGNED else ".0f"
        print(f"| {label} | {cells[0]:{fmt}} | {cells[1]:{fmt}} |")
    ok = [sum(r.ok() for r in results[b]) for b in results]
    print(f"| runs meeting every bound | {ok[0]} / {runs} | {ok[1]} / {runs} |")
    print(f"load average after: {os.getloadavg()}")
    if args.json:
        out = {
            "runs": runs,
            "figures": [label for _, label in FIGURES],
            "bauds": {
                str(b): {
                    "medians_us": {
                        label: statistics.median(r.figures()[key] for r in results[b])
                        for key, label in FIGURES
                    },
                    "runs_meeting_every_bound": sum(r.ok() for r in results[b]),
                }
                for b in results
            },
        }
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
