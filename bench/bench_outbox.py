"""The bridge outbox's throughput (issue 19): 200-byte records appended and fsynced in
batches, then read back and acked as a publisher would.

    python bench/bench_outbox.py [--records 200000] [--runs 7] [--dir DIR]

Rows (median of --runs runs, each in a fresh outbox directory under --dir, which
should be on the disk the bridge would use; the default is the system's temp dir):

* ``append+flush``: `append` in a loop, `flush` whenever `flush_due(now)` says so
  (default limits: every 4096 records or 50 ms), with the real monotonic clock;
  the final flush is included.  The bridge needs >= 20,000 updates/s end to end.
* ``append only``: the same without any flush (the write path's CPU cost).
* ``drain``: `pending(1000, after=cursor)` and `ack` of the last one, until empty,
  of the records the append+flush row left (the publisher's side, read from disk).
* ``fsync per record``: a flush after every append, on fewer records: what batching
  saves.

A measurement, not a test: nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pyrtu.outbox.outbox import Outbox, OutboxLimits

RECORD = bytes(range(200))


def append_flush(d: Path, n: int, flush: bool) -> tuple[float, Outbox]:
    ob = Outbox(d, OutboxLimits())
    clock = time.monotonic
    t0 = time.perf_counter()
    for _ in range(n):
        now = clock()
        ob.append(RECORD, now)
        if flush and ob.flush_due(now):
            ob.flush()
    if flush:
        ob.flush()
    return time.perf_counter() - t0, ob


def drain(ob: Outbox) -> tuple[float, int]:
    t0 = time.perf_counter()
    cursor, count = ob.acked, 0
    while True:
        batch = ob.pending(1000, after=cursor)
        if not batch:
            break
        cursor = batch[-1][0]
        count += len(batch)
        ob.ack(cursor)
    return time.perf_counter() - t0, count


def fsync_each(d: Path, n: int) -> float:
    with Outbox(d, OutboxLimits()) as ob:
        t0 = time.perf_counter()
        for _ in range(n):
            ob.append(RECORD, 0.0)
            ob.flush()
        return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--records", type=int, default=200_000)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()))
    ap.add_argument("--json", type=Path, help="also write the rates here")
    args = ap.parse_args(argv)
    rates: dict[str, list[float]] = {k: [] for k in ("append+flush", "append only", "drain")}
    rates["fsync per record"] = []
    n = args.records
    base = Path(tempfile.mkdtemp(prefix="bench-outbox-", dir=args.dir))
    try:
        for run in range(args.runs):
            d = base / f"run{run}"
            secs, ob = append_flush(d / "flushed", n, flush=True)
            rates["append+flush"].append(n / secs)
            secs, count = drain(ob)
            assert count == n, (count, n)
            rates["drain"].append(count / secs)
            ob.close()
            secs, ob = append_flush(d / "unflushed", n, flush=False)
            rates["append only"].append(n / secs)
            ob.close()
            m = max(200, n // 100)
            rates["fsync per record"].append(m / fsync_each(d / "each", m))
            shutil.rmtree(d)
    finally:
        shutil.rmtree(base, ignore_errors=True)
    print(f"outbox, 200-byte records, {n:,} per run, median of {args.runs} runs ({base.parent}, "
          f"Python {sys.version.split()[0]}, {os.cpu_count()} CPUs)")  # fmt: skip
    print(f"{'row':<18} {'records/s median':>17} {'min':>12} {'max':>12}")
    for name, rs in rates.items():
        med, lo, hi = (f"{v:,.0f}" for v in (statistics.median(rs), min(rs), max(rs)))
        print(f"{name:<18} {med:>17} {lo:>12} {hi:>12}")
    if args.json:
        out = {"records": n, "runs": args.runs, "dir": str(base.parent), "rates": rates}
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
