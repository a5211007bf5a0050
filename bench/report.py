"""Run every benchmark of bench/README.md once and write bench/RESULTS.md from that run.

    python bench/report.py              # (make bench) every benchmark, then RESULTS.md
    python bench/report.py --quick      # fewer rounds and shorter runs (said in the header)
    python bench/report.py --only crc,core   # these; every other section: "not run"
    python bench/report.py --render     # RESULTS.md again from bench/results/, measuring nothing

Each benchmark runs as its own command (shown in its section), writes its figures as
JSON, and the generator keeps that JSON in ``bench/results/<name>.json`` with the
command, its date, its duration and the load average around it; ``bench/results/
machine.json`` holds the machine.  RESULTS.md is rewritten entirely from those files
(bench/report_render.py): nothing in it is carried over from an earlier run, and a
target whose benchmark did not run (or failed) in this run says so instead of
quoting an older figure.  History is left to git.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
RESULTS = BENCH / "RESULTS.md"
RAW = BENCH / "results"
TIMEOUT_S = 3600.0  # one benchmark; a hung one is killed and reported as failed


@dataclass(frozen=True)
class Benchmark:
    """One benchmark script and how the generator runs it."""

    name: str  # bench/results/<name>.json, and the capability's key
    argv: tuple[str, ...]  # after ``python``, from the repository root
    quick: tuple[str, ...] = ()  # added (or replacing argv's options) with --quick
    json_flag: str = "--json"  # how the script is told where its JSON goes
    joined: bool = False  # ``--flag=PATH`` rather than ``--flag PATH``

    def command(self, quick: bool, json_name: str) -> list[str]:
        args = list(self.argv)
        extra = list(self.quick) if quick else []
        while extra:  # an option argv already has gets the quick value in its place
            opt = extra.pop(0)
            value = (
                extra.pop(0)
                if extra and opt.startswith("--") and not extra[0].startswith("--")
                else None
            )
            if value is not None and opt in args:
                args[args.index(opt) + 1] = value
            else:
                args += [opt] if value is None else [opt, value]
        out = [f"{self.json_flag}={json_name}"] if self.joined else [self.json_flag, json_name]
        return args + out


PYTEST = ("-m", "pytest", "-q", "-p", "no:cacheprovider")
BENCH_SETTINGS = ("--benchmark-min-time=0.05", "--benchmark-max-time=1.0")

#: In the order of RESULTS.md.  bench/README.md lists the same scripts as benchmarks
#: (tests/test_bench_report.py checks that every one of them is here).
BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark(
        "crc",
        (*PYTEST, "bench/bench_crc.py", *BENCH_SETTINGS),
        json_flag="--benchmark-json",
        joined=True,
    ),
    Benchmark(
        "core",
        (*PYTEST, "bench/bench_core.py", *BENCH_SETTINGS),
        json_flag="--benchmark-json",
        joined=True,
    ),
    Benchmark("serial", ("bench/run_serial.py", "--no-write")),
    Benchmark("client", ("bench/bench_client.py",), quick=("--quick",)),
    Benchmark(
        "loops",
        ("bench/bench_client.py", "--loops", "--buses", "4", "--drive", "cv100", "--rounds", "3"),
        quick=("--quick", "--rounds", "1"),
    ),
    Benchmark(
        "tcpmaster",
        (*PYTEST, "bench/bench_tcp_master.py", *BENCH_SETTINGS),
        json_flag="--benchmark-json",
        joined=True,
    ),
    Benchmark(
        "tcpasync",
        (*PYTEST, "bench/bench_tcp_async.py", *BENCH_SETTINGS),
        json_flag="--benchmark-json",
        joined=True,
    ),
    Benchmark(
        "tcpserver",
        (*PYTEST, "bench/bench_tcp_server.py", *BENCH_SETTINGS),
        json_flag="--benchmark-json",
        joined=True,
    ),
    Benchmark("slave", ("bench/run_slave.py",)),
    Benchmark("wake", ("bench/wake_floor.py",)),
    Benchmark("gateway", ("bench/run_gateway.py", "--no-write"), quick=("--seconds", "2")),
    Benchmark("poller", ("bench/bench_poller.py", "--no-write"), quick=("--seconds", "3")),
    Benchmark("many", ("bench/bench_many_devices.py",), quick=("--quick",)),
    Benchmark("manybridge", ("bench/bench_many_bridge.py",), quick=("--quick",)),
    Benchmark("decode", ("bench/bench_decode.py",), quick=("--rounds", "10")),
    Benchmark("bridge", ("bench/bench_bridge.py",), quick=("--outage", "10", "--rounds", "3")),
    Benchmark("outbox", ("bench/bench_outbox.py",), quick=("--runs", "3")),
    Benchmark(
        "sparkplug",
        ("bench/bench_sparkplug.py",),
        quick=("--outage", "10", "--rounds", "3", "--rebirths", "10"),
    ),
    Benchmark(
        "mbaps",
        ("bench/bench_mbaps.py",),
        quick=(
            *("--transactions", "500", "--connects", "30"),
            *("--stime-rounds", "1", "--stime-seconds", "1"),
        ),
    ),
    Benchmark("setrt", ("bench/bench_set_roundtrip.py",), quick=("--sets", "100")),
    Benchmark("compat", ("bench/bench_compat.py",)),
    Benchmark("capture", ("bench/bench_capture.py",), quick=("--sizes", "10,50")),
    Benchmark("vbus", ("bench/vbus_timing.py",), quick=("10",)),
    Benchmark("soak", ("bench/soak.py",), quick=("--short",)),
    Benchmark("install", ("bench/bench_install.py",), quick=("--runs", "1")),
)
BY_NAME = {b.name: b for b in BENCHMARKS}


def _first_line(argv: list[str]) -> str:
    try:
        done = subprocess.run(argv, capture_output=True, text=True, check=False, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return "not found"
    text = (done.stdout or done.stderr).strip()
    return text.splitlines()[0] if text else "not found"


def machine(quick: bool, only: list[str] | None) -> dict[str, Any]:
    """What the header says about the machine and the run, read from the machine."""
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    sys.path.insert(0, str(ROOT))
    import pyrtu

    rev = _first_line(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"])
    dirty = _first_line(["git", "-C", str(ROOT), "status", "--porcelain", "--", "pyrtu", "csrc"])
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "kernel": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "gcc": _first_line(["gcc", "--version"]),
        "libmodbus": _first_line(["pkg-config", "--modversion", "libmodbus"]),
        "backend": pyrtu.BACKEND,
        "commit": rev
        + (" (with uncommitted changes to pyrtu/ or csrc/)" if dirty != "not found" else ""),
        "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_before": list(os.getloadavg()),
        "quick": quick,
        "only": only,
    }


def run_one(bench: Benchmark, quick: bool) -> dict[str, Any]:
    """Run one benchmark; its figures and how they were made (never raises)."""
    shown = ["python", *bench.command(quick, f"{bench.name}.json")]
    record: dict[str, Any] = {
        "name": bench.name,
        "command": shlex.join(shown),
        "started": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load_before": list(os.getloadavg()),
        "quick": quick,
    }
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix=f"pyrtu-report-{bench.name}-") as tmp:
        out = Path(tmp) / f"{bench.name}.json"
        argv = [sys.executable, *bench.command(quick, str(out))]
        print(f"report.py: {record['command']}", flush=True)
        proc = subprocess.Popen(
            argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True,
        )  # fmt: skip
        try:
            log, _ = proc.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            log, _ = proc.communicate()
            record["error"] = f"killed after {TIMEOUT_S:.0f} s"
        record["returncode"] = proc.returncode
        record["duration_s"] = round(time.monotonic() - t0, 1)
        record["load_after"] = list(os.getloadavg())
        try:
            record["data"] = json.loads(out.read_text())
        except (OSError, ValueError) as exc:
            record["data"] = None
            record.setdefault("error", f"no figures ({exc.__class__.__name__})")
    if record["data"] is None or (proc.returncode != 0 and bench.name != "soak"):
        # soak.py exits 1 when a fault was not recovered: that is a figure, not a failure
        record.setdefault("error", f"exit status {proc.returncode}")
        record["log_tail"] = (log or "").strip().splitlines()[-15:]
    print(f"report.py: {bench.name}: {record['duration_s']} s, exit {proc.returncode}", flush=True)
    return record


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer rounds, shorter runs")
    ap.add_argument("--only", help=f"comma-separated, of: {', '.join(BY_NAME)}")
    ap.add_argument(
        "--render", action="store_true", help="only write RESULTS.md from bench/results/"
    )
    ap.add_argument(
        "--add",
        help="run these benchmarks (comma-separated) and add them to the kept run: each "
        "section names its own command and date, the header lists what was added later",
    )
    args = ap.parse_args(argv)
    only = args.only.split(",") if args.only else None
    added = args.add.split(",") if args.add else []
    for flag, names in (("--only", only or []), ("--add", added)):
        for name in names:
            if name not in BY_NAME:
                ap.error(f"{flag}: no benchmark {name!r} (known: {', '.join(BY_NAME)})")
    if added:
        info = json.loads((RAW / "machine.json").read_text())
        for name in added:
            record = run_one(BY_NAME[name], args.quick)
            (RAW / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")
            later = [a for a in info.get("added", []) if a["name"] != name]
            info["added"] = [*later, {"name": name, "started": record["started"]}]
        (RAW / "machine.json").write_text(json.dumps(info, indent=1) + "\n")
    elif not args.render:
        RAW.mkdir(exist_ok=True)
        for old in RAW.glob("*.json"):
            old.unlink()  # nothing of an earlier run stays beside this one
        info = machine(args.quick, only)
        (RAW / "machine.json").write_text(json.dumps(info, indent=1) + "\n")
        for bench in BENCHMARKS:
            if only is None or bench.name in only:
                record = run_one(bench, args.quick)
                (RAW / f"{bench.name}.json").write_text(json.dumps(record, indent=1) + "\n")
        info["finished"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        info["load_after"] = list(os.getloadavg())
        (RAW / "machine.json").write_text(json.dumps(info, indent=1) + "\n")
    sys.path.insert(0, str(BENCH))
    from report_render import render_dir

    RESULTS.write_text(render_dir(RAW))
    print(f"report.py: wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
