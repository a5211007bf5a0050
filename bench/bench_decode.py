"""Decoding cost per point in the poller (issue 29's target): `Point.decode` of every
type, as the scheduler calls it for each point of a block read, before and after the
register types of issue 29, in one run.

    python bench/bench_decode.py [--base REF] [--points 100] [--json FILE]

"Before" is `pyrtu/poller/points.py` and `pyrtu/pdu/data.py` as they were at
``--base`` (default: the parent of the commit that added `pyrtu/pdu/codecs.py`),
loaded from git into this process under other names; "after" is the working tree.
Each row decodes ``--points`` points of one type laid out one after the other in a
block (as a poll of a device's block delivers them) and reports the best of
``--rounds`` rounds (every case once per round, interleaved), in nanoseconds per
point (``--json``: the figures as JSON, ``{"ns_per_point": {"before uint16": ...,
"after uint16": ...}}``).  Targets: the existing types not slower than
before; every new type within 1.5x of uint16's cost (before, today's; the ratio
to uint16 after is shown too).  bench/report.py puts it in the section "Point
decoding" of bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import platform
import subprocess
import sys
import timeit
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from pyrtu.poller.points import Point  # noqa: E402

HEADING = "## Point decoding cost (issue 29)"


def default_base() -> str:
    added = subprocess.run(
        ["git", "log", "--diff-filter=A", "--format=%H", "--", "pyrtu/pdu/codecs.py"],
        cwd=ROOT, capture_output=True, text=True, check=True,
    ).stdout.split()  # fmt: skip
    return f"{added[-1]}^" if added else "HEAD"


def old_point_class(base: str) -> Any:
    """`Point` of ``base``: its points.py and data.py from git, as modules of their own."""

    def load(path: str, name: str, source_fix: Callable[[str], str] = lambda s: s) -> Any:
        text = subprocess.run(
            ["git", "show", f"{base}:{path}"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
        module = types.ModuleType(name)
        module.__file__ = f"<{base}:{path}>"
        sys.modules[name] = module
        exec(compile(source_fix(text), module.__file__, "exec"), module.__dict__)
        return module

    load("pyrtu/pdu/data.py", "_old_data")
    old = load(
        "pyrtu/poller/points.py",
        "_old_points",
        lambda s: s.replace("from pyrtu.pdu.data import", "from _old_data import"),
    )
    return old.Point


#: (row, type, extra point keys, registers per point, the existing types' before) ...
CASES: list[tuple[str, dict[str, Any], int, bool]] = [
    ("uint16", {}, 1, True),
    ("int16", {"type": "int16"}, 1, True),
    ("uint16 scaled (0.1)", {"scale": 0.1}, 1, True),
    ("uint32", {"type": "uint32"}, 2, True),
    ("int32", {"type": "int32"}, 2, True),
    ("float32", {"type": "float32"}, 2, True),
    ("float32 CDAB", {"type": "float32", "order": "CDAB"}, 2, True),
    ("string (4 registers)", {"type": "string", "count": 4}, 4, True),
    ("bool (coils)", {"table": "coils"}, 1, True),
    ("int8", {"type": "int8"}, 1, False),
    ("uint8 low", {"type": "uint8", "order": "low"}, 1, False),
    ("int64", {"type": "int64"}, 4, False),
    ("uint64 GHEFCDAB", {"type": "uint64", "order": "GHEFCDAB"}, 4, False),
    ("float16", {"type": "float16"}, 1, False),
    ("float64", {"type": "float64"}, 4, False),
    ("float64 HGFEDCBA", {"type": "float64", "order": "HGFEDCBA"}, 4, False),
    ("bcd16", {"type": "bcd16"}, 1, False),
    ("bcd32", {"type": "bcd32"}, 2, False),
    ("string1 (4 registers)", {"type": "string1", "count": 4}, 4, False),
    ("int16 byte-swapped (BA)", {"type": "int16", "order": "BA"}, 1, False),
    ("bit", {"bit": 5}, 1, False),
    ("bit field", {"bits": [4, 3]}, 1, False),
    ("enum", {"enum": {"0": "off", "1": "heat", "2": "cool"}}, 1, False),
    ("uint16 error_value", {"error_value": 0xFFFF}, 1, False),
    ("float32 error_value nan", {"type": "float32", "error_value": math.nan}, 2, False),
]


def runner(point_class: Any, keys: dict[str, Any], width: int, n: int) -> Callable[[], None]:
    """Decoding every point of a block of ``n`` points of one type."""
    kw = {"bus": "b", "slave": 1, "table": "holding", **keys}
    points = [point_class(f"p{i}", address=i * width, **kw) for i in range(n)]
    block: Sequence[Any]
    if kw["table"] == "coils":
        block = [i % 3 == 0 for i in range(n * width)]
    else:  # printable, valid BCD and small enough for every type's labels
        block = [0x3132 if "string" in str(keys.get("type")) else i % 3 for i in range(n * width)]

    def run() -> None:
        for p in points:
            p.decode(block, 0)

    return run


def measure(runs: dict[str, Callable[[], None]], n: int, rounds: int) -> dict[str, float]:
    """ns per point of each run: the best of ``rounds`` rounds, the runs interleaved in
    each round (so that a busy moment of the machine hits them all alike)."""
    best = dict.fromkeys(runs, math.inf)
    for _ in range(rounds):
        for key, run in runs.items():
            best[key] = min(best[key], timeit.timeit(run, number=20) / 20 / n * 1e9)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("--base", default=None, help="the git revision of 'before'")
    ap.add_argument("--points", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=30, help="rounds of every case, interleaved")
    ap.add_argument("--json", type=Path, help="also write the figures here (ns per point)")
    args = ap.parse_args()
    base = args.base or default_base()
    old_point = old_point_class(base)
    runs: dict[str, Callable[[], None]] = {}
    for label, keys, width, existed in CASES:
        runs["after " + label] = runner(Point, keys, width, args.points)
        if existed:
            runs["before " + label] = runner(old_point, keys, width, args.points)
    ns = measure(runs, args.points, args.rounds)
    uint16_after, uint16_before = ns["after uint16"], ns["before uint16"]
    rows = []
    table_rows: list[dict[str, object]] = []
    for label, _keys, _width, existed in CASES:
        after = ns["after " + label]
        before = ns.get("before " + label)
        if before is not None:
            verdict = "ok" if after <= before * 1.05 else "SLOWER"
            versus = f"{after / before:.2f}x before"
        elif label.startswith("string1"):  # a string of the same registers is the yardstick
            ratio = after / ns["before string (4 registers)"]
            verdict = "ok" if ratio <= 1.5 else "above 1.5x"
            versus = (
                f"{ratio:.2f}x string before, {after / ns['after string (4 registers)']:.2f}x after"
            )
        else:
            ratio = after / uint16_before
            verdict = "ok" if ratio <= 1.5 else "above 1.5x"
            versus = f"{ratio:.2f}x uint16 before, {after / uint16_after:.2f}x after"
        shown = "-" if before is None else f"{before:.0f}"
        rows.append(f"| {label} | {shown} | {after:.0f} | {versus} | {verdict} |")
        table_rows.append(
            {"type": label, "before": before, "after": after, "versus": versus,
             "ok": verdict == "ok", "existed": existed}
        )  # fmt: skip
    rev = subprocess.run(["git", "rev-parse", "--short", base], cwd=ROOT, capture_output=True,
                         text=True, check=False).stdout.strip() or base  # fmt: skip
    text = "\n".join([
        HEADING,
        "",
        f"`python bench/bench_decode.py` ({datetime.date.today()}, {platform.machine()},"
        f" Python {platform.python_version()}, {args.points} points per block, best of"
        f" {args.rounds} interleaved rounds); before: `Point` of {rev}, after: the working"
        " tree, in one process.",
        "Targets: the existing types not slower than before (within 5 % noise); the",
        "new types within 1.5x of uint16's cost (today's, before: the verdict; the ratio",
        "to the faster uint16 of after is shown too). A string's row is 4 registers per",
        "point: string1 is judged against string.",
        "",
        "| type | before, ns/point | after, ns/point | ratio | target |",
        "|---|---|---|---|---|",
        *rows,
        "",
    ])  # fmt: skip
    print(text)
    if args.json:
        doc = {
            "base": rev, "points": args.points, "rounds": args.rounds, "ns_per_point": ns,
            "rows": table_rows,
        }  # fmt: skip
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
