"""A thousand Modbus TCP devices polled by one poller process (issue 30, item 3).

    python bench/bench_many_devices.py [--devices 1000] [--registers 30]
        [--rates 1,10] [--seconds 20] [--warmup 4] [--quick] [--also KINDS]
        [--json FILE]

The devices: one ``pyrtu simulate --template T --tcp 127.0.0.1:FIRST-LAST``
process (a device of ``--registers`` holding registers on every port of the
range; its own process, its CPU is not the poller's).  The poller: a `Poller` in
a process of its own (this script with ``--child``), on the event loop ``pyrtu
poll --config`` runs (`pyrtu.drivers.aio.run` with the configuration's
descriptors), one ``tcp://`` bus per device and one read of all its registers
every ``1 / rate`` seconds, the buses on the poller's mux (``master="auto"``:
`pyrtu.poller.muxdrive`).  At every rate the healthy run is repeated with every
bus on an `AsyncMaster` of its own (``own masters``: ``master="aio"``, the path
before the mux) and with ``[connect] lateness = 0.01`` (``lateness 1 %``: the
polls' wake-up grid of 1 % of the interval, not 2.5 %), like for like in one run
(``--also``).  ``--also`` may also name runs not made by default: ``lateness 5 %``
and ``lateness 10 %`` (wider grids), and ``breakdown``: the healthy run with the
event loop thread's time per answered read split by where it goes (the mux
driver's wake-up and collection callbacks, and inside them the C calls submit,
service and take: `time.thread_time` around each call, which itself costs a
little).  That process measures itself over ``--seconds``
after ``--warmup`` (every device connected and polling):

* its CPU time (user + system, `resource.getrusage`, every thread) over the wall
  time: % of one core; and its event loop's thread's alone (``time.thread_time``);
* every device's achieved period (the mean gap between its answered reads, from
  `Poller.on_latency`) over its interval: the worst device, the median, and the
  largest single gap;
* its resident memory (``VmRSS``) with the poller running, less what it was
  before the configuration was loaded, per device; and how much it grew over
  the second half of the measurement (bounded memory: nothing kept per
  transaction beyond each slave's last 1024 latencies);
* the ramp: seconds from the start until every device (but the bad one) answered;
* its time waiting for a CPU while it could run (``/proc/self/schedstat``'s run
  queue wait), as a part of the time it had work (that wait and its CPU time): a
  figure taken on a loaded machine says so (a poller that waited most of its time
  for a CPU falls behind for want of one, not of anything it waits on);
* the latency of the reads (median, 99th percentile), their timeouts and the
  ports' outages.

The warm-up (``--warmup``) begins once every device answered.

At the first rate the run is repeated with the device in the middle of the
range (500 of 1,000) silent (a socket of this script's that accepts and never
answers) and with it refusing (a port nothing listens on; ``--bad`` picks which):
the other devices' periods are compared with the healthy run's.

bench/report.py runs it (``--json``) for bench/RESULTS.md; the summary goes to stdout.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import resource
import shlex
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from array import array
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
TIMEOUT = 1.0  # each bus's timeout (a silent device's reads end after it)
#: the healthy run again, the poller otherwise (``--also``): every bus on an
#: `AsyncMaster` of its own (no mux), and the mux with polls at most 1 % late
ALSO: dict[str, dict[str, Any]] = {
    "own masters": {"master": "aio"},
    "lateness 1 %": {"lateness": 0.01},
}
#: runs ``--also`` may name that it does not run by default: wider wake-up grids, and
#: the healthy run with the event loop's time split by where it goes (``breakdown``)
MORE: dict[str, dict[str, Any]] = {
    "lateness 5 %": {"lateness": 0.05},
    "lateness 10 %": {"lateness": 0.1},
    "breakdown": {"breakdown": True},
}
#: the parts ``breakdown`` times in the poller process (`time.thread_time` around
#: each call): the mux driver's two callbacks, and the C calls inside them
BREAKDOWN = (
    ("wake", "pyrtu.poller.muxdrive", "MuxDriver", "_wake"),
    ("collect", "pyrtu.poller.muxdrive", "MuxDriver", "_collected"),
    ("submit", "pyrtu.tcp._cmux", "CMux", "submit"),
    ("service", "pyrtu.tcp._cmux", "CMux", "service"),
    ("take", "pyrtu.tcp._cmux", "CMux", "take"),
)


def template_text(registers: int) -> str:
    """A device of ``registers`` holding registers 0.. (uint16 points r0, r1...)."""
    lines = ["[device]", 'vendor = "pyrtu bench"', 'model = "many"', "address = 1", ""]
    for i in range(registers):
        lines += ["[[point]]", f'name = "r{i}"', 'table = "holding"', f"address = {i}"]
        lines += [f"initial = {(i * 37) % 65536}", ""]
    return "\n".join(lines)


def config_text(
    urls: list[str], registers: int, interval: float, lateness: float | None = None
) -> str:
    """One ``tcp://`` bus per device, its registers as points read every ``interval``
    (``lateness``: the ``[connect]`` key, None: its default)."""
    out = [f'[defaults]\ninterval = {interval}\ntable = "holding"\nslave = 1\n']
    if lateness is not None:
        out.append(f"[connect]\nlateness = {lateness}\n")
    for i, url in enumerate(urls):
        out.append(f'[[bus]]\nname = "d{i}"\nport = "{url}"\ntimeout = {TIMEOUT}\n')
        for r in range(registers):
            out.append(f'[[point]]\nname = "d{i}.r{r}"\nbus = "d{i}"\naddress = {r}\n')
    return "\n".join(out)


def rss_kib(pid: int | str = "self") -> int:
    """The resident memory (``VmRSS``) of process ``pid`` (this one by default), KiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS in /proc/{pid}/status")


def child_env() -> dict[str, str]:
    """This environment, with this tree first on ``PYTHONPATH``: what the processes
    started here (the simulator, the poller, the bridge) import pyrtu from."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return env


def cpu_seconds() -> float:
    use = resource.getrusage(resource.RUSAGE_SELF)
    return use.ru_utime + use.ru_stime


# ---------------------------------------------------------------- the poller process


def run_queue_s() -> float:
    """Seconds this process's thread waited for a CPU while it could run (Linux)."""
    return int(Path("/proc/self/schedstat").read_text().split()[1]) / 1e9


def timed_parts(measuring: Callable[[], bool]) -> dict[str, float]:
    """`BREAKDOWN`'s calls wrapped: the thread time spent in each, while
    ``measuring()``, added up in the dict returned (seconds)."""
    import importlib

    spent = {name: 0.0 for name, *_ in BREAKDOWN}
    clock = time.thread_time

    def timed(name: str, f: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            t0 = clock()
            try:
                return f(*args, **kwargs)
            finally:
                if measuring():
                    spent[name] += clock() - t0

        return call

    for name, module, cls, method in BREAKDOWN:
        owner = getattr(importlib.import_module(module), cls)
        setattr(owner, method, timed(name, getattr(owner, method)))
    return spent


def child(
    config: str,
    warmup: float,
    seconds: float,
    out: Path,
    bad: str | None,
    master: str,
    breakdown: bool = False,
) -> None:
    """Run the poller of ``config`` (``bad``: the bus that never answers, if any);
    write what it measured on itself to ``out`` (``breakdown``: with `timed_parts`)."""
    from pyrtu.drivers.aio import run as aio_run
    from pyrtu.poller import Poller, PortState, load_config

    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    before = rss_kib()
    cfg = load_config(config)
    buses = [b.name for b in cfg.buses]
    interval = min(p.interval for p in cfg.points)
    # (the measurement's own record of every answer: 8 bytes a number, not a float
    # object, since the process's memory growth is measured meanwhile)
    answers: dict[str, array[float]] = {name: array("d") for name in buses}
    measuring = False
    clock = time.monotonic
    first: dict[str, float] = {}
    latencies: array[float] = array("d")

    def answered(bus: str, slave: int, seconds: float) -> None:
        if bus not in first:
            first[bus] = clock()
        if measuring:
            answers[bus].append(clock())
            latencies.append(seconds)

    outages: list[str] = []
    spent = timed_parts(lambda: measuring) if breakdown else None

    def event(ev: Any) -> None:
        if isinstance(ev, PortState) and not ev.up:
            outages.append(f"{ev.bus}: {ev.error}")

    async def main() -> dict[str, Any]:
        nonlocal measuring
        poller = Poller(cfg, master=master)
        poller.on_latency(answered)
        poller.on_event(event)
        import asyncio

        started = clock()
        await poller.start()
        try:
            # every device but the bad one answered (at most a minute), then the warm-up
            needed = [name for name in buses if name != bad]
            while clock() < started + 60 and not all(name in first for name in needed):
                await asyncio.sleep(0.05)
            answering = [first[name] for name in needed if name in first]
            ramp = max(answering) - started if len(answering) == len(needed) else None
            await asyncio.sleep(warmup)
            rss_start = rss_kib()
            measuring = True
            cpu0, t0, queued0 = cpu_seconds(), clock(), run_queue_s()
            loop0 = time.thread_time()
            await asyncio.sleep(seconds / 2)
            rss_mid = rss_kib()
            await asyncio.sleep(seconds / 2)
            cpu1, t1, queued1 = cpu_seconds(), clock(), run_queue_s()
            loop1 = time.thread_time()
            measuring = False
            rss_end = rss_kib()
            summary = poller.summary()
        finally:
            await poller.stop()
        return {
            "cpu_s": cpu1 - cpu0,
            "loop_cpu_s": loop1 - loop0,
            "run_queue_s": queued1 - queued0,
            "unanswered_at_ramp": len(needed) - len(answering),
            "wall_s": t1 - t0,
            "rss_before_kib": before,
            "rss_start_kib": rss_start,
            "rss_end_kib": rss_end,
            "ports_down": sum(1 for b in summary["buses"] if b["port_state"] == "down"),
            "outages": outages,
            "timeouts": sum(s["timeouts"] for s in summary["slaves"]),
            "ramp_s": ramp,
            "rss_mid_kib": rss_mid,
            "spent_s": spent,
        }

    result = aio_run(main(), descriptors=len(cfg.buses))
    periods: dict[str, float | None] = {}
    gaps: dict[str, float | None] = {}
    for name, times in answers.items():
        if len(times) >= 2:
            periods[name] = (times[-1] - times[0]) / (len(times) - 1) / interval
            gaps[name] = max(b - a for a, b in itertools.pairwise(times)) / interval
        else:
            periods[name] = gaps[name] = None
    latencies = array("d", sorted(latencies))
    result["latency_ms"] = (
        {
            q: 1000 * latencies[min(len(latencies) - 1, int(len(latencies) * f))]
            for q, f in (("p50", 0.5), ("p99", 0.99))
        }
        if latencies
        else None
    )
    result.update(interval=interval, periods=periods, gaps=gaps,
                  answers={n: len(t) for n, t in answers.items()})  # fmt: skip
    out.write_text(json.dumps(result))


# ---------------------------------------------------------------- the devices


class Silent:
    """A TCP port that accepts every connection and never answers (a thread)."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(64)
        self.port = self.sock.getsockname()[1]
        self.held: list[socket.socket] = []
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.held.append(conn)  # read nothing, answer nothing

    def close(self) -> None:
        self.sock.close()
        for conn in self.held:
            conn.close()


def refused_port() -> int:
    """A loopback port nothing listens on (bound, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def proc_cpu(pid: int) -> float:
    """CPU seconds (user + system) of process ``pid`` so far, from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def start_devices(template: Path, devices: int, *options: str) -> tuple[subprocess.Popen[str], int]:
    """``pyrtu simulate`` on ``devices`` consecutive free ports (with ``options``, as
    ``--vary 0.5``): (process, first port)."""
    env = child_env()
    low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    err = ""
    for _ in range(20):  # below the ephemeral ports: no connection of anyone's holds them
        first = random.randrange(10000, max(10001, low - devices))
        spec = f"127.0.0.1:{first}-{first + devices - 1}"
        proc = subprocess.Popen(
            [sys.executable, "-m", "pyrtu", "simulate", "--template", str(template),
             "--tcp", spec, *options, "--json"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        )  # fmt: skip
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if line and json.loads(line).get("type") == "ready":
            return proc, first
        proc.wait(30)
        err = proc.stderr.read() if proc.stderr else ""
        if "cannot listen" not in err:
            raise RuntimeError(f"pyrtu simulate did not start: {err.strip()}")
    raise RuntimeError(f"no free range of ports found for pyrtu simulate: {err.strip()}")


def run_poller(
    urls: list[str],
    registers: int,
    rate: float,
    warmup: float,
    seconds: float,
    sim: int,
    bad: int | None = None,
    master: str = "auto",
    lateness: float | None = None,
    breakdown: bool = False,
) -> dict[str, Any]:
    """One poller process over ``urls`` (``bad``: the rank of the device that never
    answers, if any; ``master``: `Poller`'s; ``lateness``: the ``[connect]`` key):
    what it measured, with the simulator's CPU."""
    with tempfile.TemporaryDirectory(prefix="pyrtu-many-") as tmp:
        config = Path(tmp) / "many.toml"
        config.write_text(config_text(urls, registers, 1.0 / rate, lateness))
        out = Path(tmp) / "child.json"
        env = child_env()
        sim0 = proc_cpu(sim)
        t0 = time.monotonic()
        done = subprocess.run(
            [sys.executable, __file__, "--child", str(config), "--warmup", str(warmup),
             "--seconds", str(seconds), "--out", str(out), "--master", master,
             *(() if bad is None else ("--bad-bus", f"d{bad}")),
             *(("--breakdown",) if breakdown else ())],
            env=env, capture_output=True, text=True, timeout=warmup + seconds + 300, check=False,
        )  # fmt: skip
        wall = time.monotonic() - t0
        sim_cpu = proc_cpu(sim) - sim0
        if done.returncode != 0:
            raise RuntimeError(f"the poller process failed: {done.stderr.strip()[-2000:]}")
        result: dict[str, Any] = json.loads(out.read_text())
    result["simulator_cpu_pct"] = 100.0 * sim_cpu / wall
    return result


def judge(result: dict[str, Any], devices: int, skip: int | None = None) -> dict[str, Any]:
    """The figures of one run (``skip``: the bad device, left out of the periods)."""
    names = [f"d{i}" for i in range(devices) if i != skip]
    periods = [result["periods"][n] for n in names]
    gaps = [result["gaps"][n] for n in names]
    measured = [p for p in periods if p is not None]
    per_device = (result["rss_start_kib"] - result["rss_before_kib"]) / devices
    answered = sum(result["answers"].values())
    spent = result.get("spent_s")
    return {
        # ``breakdown``: µs of the loop's thread per answered read, by part
        "breakdown_us": None
        if not spent or not answered
        else {
            **{name: 1e6 * s / answered for name, s in spent.items()},
            "loop": 1e6 * result["loop_cpu_s"] / answered,
        },
        "cpu_pct": 100.0 * result["cpu_s"] / result["wall_s"],
        "loop_cpu_pct": 100.0 * result["loop_cpu_s"] / result["wall_s"],
        # of the time the poller had work, the part it waited for a CPU
        "run_queue_pct": 100.0 * result["run_queue_s"] / (result["run_queue_s"] + result["cpu_s"]),
        "seconds": result["wall_s"],
        "devices_measured": len(measured),
        "devices_unmeasured": len(periods) - len(measured),
        "period_median": statistics.median(measured) if measured else None,
        "period_min": min(measured) if measured else None,
        "period_max": max(measured) if measured else None,
        "gap_max": max((g for g in gaps if g is not None), default=None),
        "within_10pct": sum(1 for p in measured if abs(p - 1.0) <= 0.10),
        "rss_per_device_kib": per_device,
        "rss_growth_kib": result["rss_end_kib"] - result["rss_mid_kib"],
        "ramp_s": result["ramp_s"],
        "unanswered_at_ramp": result["unanswered_at_ramp"],
        "rss_kib": result["rss_start_kib"],
        "simulator_cpu_pct": result["simulator_cpu_pct"],
        "ports_down": result["ports_down"],
        "outages": len(result["outages"]),
        "timeouts": result["timeouts"],
        "latency_ms": result["latency_ms"],
    }


def bad_device(devices: int) -> int:
    """The rank of the device made silent or refusing: the middle of the range."""
    return devices // 2


def compare(base: dict[str, Any], bad: dict[str, Any], devices: int) -> dict[str, Any]:
    """The others' periods with the bad device against the healthy run's."""
    ratios = []
    skip = bad_device(devices)
    for i in range(devices):
        if i == skip:
            continue
        a, b = base["periods"][f"d{i}"], bad["periods"][f"d{i}"]
        if a is not None and b is not None:
            ratios.append(b / a)
    return {
        "others_median_ratio": statistics.median(ratios),
        "others_worst_ratio": max(ratios, key=lambda r: abs(r - 1.0)),
        "others_within_5pct": sum(1 for r in ratios if abs(r - 1.0) <= 0.05),
        "others": len(ratios),
        "bad_answers": bad["answers"][f"d{skip}"],
    }


def measure(args: argparse.Namespace) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="pyrtu-many-") as tmp:
        template = Path(tmp) / "many.toml"
        template.write_text(template_text(args.registers))
        sim, first = start_devices(template, args.devices)
        silent = Silent()
        try:
            urls = [f"tcp://127.0.0.1:{first + i}" for i in range(args.devices)]
            runs: dict[str, Any] = {}
            for rate in args.rates:
                print(f"bench_many_devices: {args.devices} devices at {rate:g} Hz", flush=True)
                raw = run_poller(urls, args.registers, rate, args.warmup, args.seconds, sim.pid)
                entry: dict[str, Any] = {"healthy": judge(raw, args.devices)}
                for kind, how in {**ALSO, **MORE}.items():  # the same devices, otherwise
                    if kind in args.also:
                        print(f"bench_many_devices: {kind}", flush=True)
                        other = run_poller(urls, args.registers, rate, args.warmup,
                                           args.seconds, sim.pid, **how)  # fmt: skip
                        entry[kind] = judge(other, args.devices)
                skip = bad_device(args.devices)
                if rate == args.rates[0] and args.devices >= 2:
                    for kind in args.bad:
                        port = silent.port if kind == "silent" else refused_port()
                        print(f"bench_many_devices: device {skip} {kind}", flush=True)
                        bad_urls = list(urls)
                        bad_urls[skip] = f"tcp://127.0.0.1:{port}"
                        bad = run_poller(bad_urls, args.registers, rate, args.warmup,
                                         args.seconds, sim.pid, skip)  # fmt: skip
                        entry[kind] = {**judge(bad, args.devices, skip),
                                       **compare(raw, bad, args.devices)}  # fmt: skip
                runs[f"{rate:g}"] = entry
        finally:
            silent.close()
            sim.send_signal(signal.SIGTERM)
            try:
                sim.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                sim.kill()
                sim.communicate()
    return runs


def summary(doc: dict[str, Any]) -> str:
    lines = [f"{doc['devices']} devices x {doc['registers']} registers, {doc['seconds']:g} s"]
    for rate, entry in doc["runs"].items():
        for kind, f in entry.items():
            ramp = (
                f"{f['ramp_s']:.1f} s"
                if f["ramp_s"] is not None
                else f"not within 60 s ({f['unanswered_at_ramp']} not yet)"
            )
            line = (
                f"{rate:>4} Hz {kind:12} CPU {f['cpu_pct']:5.1f} % of a core "
                f"({f['loop_cpu_pct']:.1f} % in the event loop's thread; waited for one "
                f"{f['run_queue_pct']:.0f} % of the time it had work); period "
                f"median {f['period_median']:.3f}, worst {f['period_max']:.3f} of the interval "
                f"({f['within_10pct']}/{f['devices_measured']} within 10 %), largest gap "
                f"{f['gap_max']:.2f}; {f['rss_per_device_kib']:.1f} KiB per device "
                f"(grew {f['rss_growth_kib']} KiB); simulator {f['simulator_cpu_pct']:.0f} %; "
                f"all answering after {ramp}; latency p50/p99 "
                f"{f['latency_ms']['p50']:.1f}/{f['latency_ms']['p99']:.1f} ms; "
                f"{f['timeouts']} timeouts, {f['outages']} outages"
            )
            if f.get("breakdown_us"):
                line += "; µs per read: " + ", ".join(
                    f"{k} {v:.1f}" for k, v in f["breakdown_us"].items()
                )
            if "others_median_ratio" in f:
                line += (
                    f"; others' periods x{f['others_median_ratio']:.4f} (worst "
                    f"x{f['others_worst_ratio']:.4f}, {f['others_within_5pct']}/{f['others']} "
                    "within 5 %)"
                )
            lines.append(line)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=1000)
    ap.add_argument("--registers", type=int, default=30)
    ap.add_argument("--rates", default="1,10", help="polls per second of each device")
    ap.add_argument("--seconds", type=float, default=20.0, help="measured, per run")
    ap.add_argument("--warmup", type=float, default=4.0, help="before measuring, per run")
    ap.add_argument("--quick", action="store_true", help="--seconds 8 --warmup 3")
    ap.add_argument(
        "--bad",
        default="silent,refusing",
        help="the runs with one bad device at the first rate: silent, refusing (none: no such run)",
    )
    ap.add_argument(
        "--also",
        default=",".join(ALSO),
        # the kinds name percentages; argparse formats help with %
        help=f"the healthy runs again, the poller otherwise: {', '.join(ALSO)} (the default), "
        f"{', '.join(MORE)} (none: no such run)".replace("%", "%%"),
    )
    ap.add_argument("--json", type=Path, default=None, help="also save the figures here")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--bad-bus", help=argparse.SUPPRESS)
    ap.add_argument("--breakdown", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--master", default="auto", help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        child(args.child, args.warmup, args.seconds, args.out, args.bad_bus, args.master,
              args.breakdown)  # fmt: skip
        return
    if args.quick:
        args.seconds, args.warmup = 8.0, 3.0
    args.rates = [float(r) for r in args.rates.split(",")]
    args.bad = [] if args.bad == "none" else args.bad.split(",")
    args.also = [] if args.also == "none" else args.also.split(",")
    if any(kind not in ALSO and kind not in MORE for kind in args.also):
        ap.error(f"--also: {', '.join([*ALSO, *MORE])} or none, not {','.join(args.also)!r}")
    if any(kind not in ("silent", "refusing") for kind in args.bad):
        ap.error(f"--bad: silent, refusing or none, not {','.join(args.bad)!r}")
    runs = measure(args)
    doc = {
        "command": shlex.join(["python", "bench/bench_many_devices.py", *sys.argv[1:]]),
        "devices": args.devices,
        "registers": args.registers,
        "seconds": args.seconds,
        "warmup": args.warmup,
        "bad_device": bad_device(args.devices),
        "runs": runs,
    }
    print(summary(doc))
    if args.json:
        args.json.write_text(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
