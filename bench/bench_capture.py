"""Peak memory (RSS) of reading captures: ``pyrtu sniff --capture`` and the
streaming API (`pyrtu.vbus.capture_frames`), on valid captures of 10 MB and
200 MB, on a valid header followed by 20 MB of random bytes (damaged: refused at
the first record), and on 20 MB of well-formed records carrying random bytes
(line noise: every byte goes through the framer's discard path).

Each case runs in its own process, its peak measured by GNU time (``/usr/bin/time -f
%M``, the maximum resident set size of the command itself; Debian's ``time``)::

    .venv/bin/python bench/bench_capture.py [--sizes 10,200] [--dir /tmp]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import capsynth  # noqa: E402

API = (
    "import sys; from pyrtu.vbus.capture import capture_frames;"
    " n = sum(1 for _ in capture_frames(sys.argv[1])); print(n)"
)


TIME = "/usr/bin/time"


def run(cmd: list[str]) -> tuple[float, float, int]:
    """(peak RSS in MB, seconds, exit code) of a child process."""
    # GNU time execs the command from its own small process: the peak it reports is the
    # command's.  getrusage(RUSAGE_CHILDREN) here would carry this (large) process's RSS,
    # which Linux keeps in ru_maxrss across the fork and exec.
    if not os.path.exists(TIME):
        raise SystemExit(f"{TIME} (GNU time) is needed: apt-get install time (make setup)")
    with tempfile.NamedTemporaryFile("r", suffix=".rss") as out:
        t = time.perf_counter()
        proc = subprocess.run(
            [TIME, "-f", "%M", "-o", out.name, *cmd],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        elapsed = time.perf_counter() - t
        kb = int(out.read().strip().splitlines()[-1])
    return kb / 1024, elapsed, proc.returncode


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="10,200", help="valid capture sizes in MB")
    ap.add_argument("--random", type=int, default=20, help="MB of random bytes after a header")
    ap.add_argument(
        "--noise", type=int, default=20, help="MB of well-formed records of random bytes"
    )
    ap.add_argument("--dir", default=None)
    ap.add_argument("--cli-max", type=int, default=200, help="largest size sniffed by the CLI")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args()
    tmp = Path(args.dir or tempfile.mkdtemp(prefix="pyrtu-bench-cap-"))
    py = sys.executable
    rows = []
    base = run([py, "-c", "import pyrtu.vbus.capture"])
    rows.append(("python + import pyrtu.vbus.capture", "-", base))
    rnd = tmp / "random.cap"
    with open(rnd, "wb") as f:
        capsynth.write_random_tail(f, args.random * 1_000_000)
    rows.append(
        (
            f"sniff --capture: header + {args.random} MB random",
            "exit 3 expected",
            run([py, "-m", "pyrtu", "sniff", "--capture", str(rnd)]),
        )
    )
    rows.append(
        (
            f"capture_frames: header + {args.random} MB random",
            "CaptureError expected",
            run([py, "-c", API, str(rnd)]),
        )
    )
    rnd.unlink()
    noise = tmp / "noise.cap"
    with open(noise, "wb") as f:
        capsynth.write_random_records(f, args.noise * 1_000_000)
    rows.append(
        (f"capture_frames: {args.noise} MB of noise records", "", run([py, "-c", API, str(noise)]))
    )
    rows.append(
        (
            f"sniff --capture --json: {args.noise} MB noise",
            "",
            run([py, "-m", "pyrtu", "sniff", "--capture", str(noise), "--json"]),
        )
    )
    noise.unlink()
    for mb in (int(s) for s in args.sizes.split(",")):
        path = tmp / f"valid{mb}.cap"
        with open(path, "wb") as f:
            frames = capsynth.write_valid(f, mb * 1_000_000, registers=125)
        rows.append(
            (f"capture_frames: valid {mb} MB", f"{frames} frames", run([py, "-c", API, str(path)]))
        )
        if mb <= args.cli_max:
            rows.append(
                (
                    f"sniff --capture --json: valid {mb} MB",
                    f"{frames} frames",
                    run([py, "-m", "pyrtu", "sniff", "--capture", str(path), "--json"]),
                )
            )
        path.unlink()
    print(f"{'case':<46} {'note':<22} {'peak RSS':>9} {'time':>8} exit")
    for name, note, (rss, secs, code) in rows:
        print(f"{name:<46} {note:<22} {rss:7.1f} MB {secs:7.1f} s {code}")
    if args.json:
        out = [
            {"case": name, "note": note, "peak_rss_mb": rss, "seconds": secs, "exit": code}
            for name, note, (rss, secs, code) in rows
        ]
        args.json.write_text(json.dumps({"rows": out}, indent=1) + "\n")
    os.rmdir(tmp) if not any(tmp.iterdir()) else None


if __name__ == "__main__":
    main()
