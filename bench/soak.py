"""Soak run: the poller, the gateway and simulated drives under faults, unattended.

    python bench/soak.py --minutes 5                 # both baud rates, the full run
    python bench/soak.py --short --json soak.json    # the short version CI runs

Per baud rate (19200 and 115200 by default) it builds, on the virtual bus:

* bus P: ``--drives`` simulated CFW701 drives (addresses 1..N) and the poller
  (``pyrtu poll --config F --json --all``, a subprocess) as master;
* bus G: two of the same drives' processes serve a second drive each on bus G, whose
  master is the gateway (``pyrtu gateway --json``, a subprocess);
* the drives are ``pyrtu simulate`` processes (one per address, one ``--port`` on bus P
  and, for the first two, one on bus G), started ``--state stopped`` so that the
  registers read have known values: the status word P680, the alarm and fault P048 and
  P049, the ramp times P100..P103;
* seeded bit errors on every drop (``--bit-flip-rate``);
* well-behaved Modbus TCP clients on the gateway alternating a short read, a long
  read and a long FC 16 write (which a CFW701 refuses with an exception: a long
  request, then short ones again), and ``--abusers`` abusive ones: idle, one byte a
  second, garbage, half headers, each reconnecting when it is closed;
* every ``--cycle`` seconds one fault: a drive's drop, the poller's drop or the
  gateway's drop unplugged (mid-frame) and plugged back ``--down`` seconds later.

It reports faults injected and recovered, the time from the replug to the first good
value through the path that lost it (the poller's update for that slave, the
gateway's answer for that unit), wrong values (a value that differs from what the
drive holds: must be 0), well-behaved clients refused or cut off, and the resident
memory of every process at the start and the end (and its peak).  Exit status: 0 when
every fault recovered and no value was wrong, 1 otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from pyrtu.vbus import Faults, VirtualBus  # noqa: E402

PYRTU = [sys.executable, "-m", "pyrtu"]
#: registers whose values a stopped CFW701 keeps (address: count)
KNOWN = {680: 1, 48: 2, 100: 4}
RECOVER_LIMIT = 45.0  # s: longer than the longest back-off (30 s) plus a probe


@dataclass
class Fault:
    kind: str  # drive, poller, gateway, gwdrive
    target: int  # slave / unit address, 0 for a master
    unplugged: float
    replugged: float = 0.0
    recovered: float = 0.0

    @property
    def recovery(self) -> float | None:
        return self.recovered - self.replugged if self.recovered else None


@dataclass
class Tally:
    updates: int = 0
    wrong: list[str] = field(default_factory=list)
    gw_answers: int = 0
    gw_exceptions: int = 0
    gw_errors: int = 0
    gw_error_examples: list[str] = field(default_factory=list)
    gw_refused: int = 0
    abuser_connects: int = 0
    abuser_closed: int = 0
    events: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    #: faults replugged and waiting for their first good value, by the path that
    #: shows it: ("slave", s) and ("poller", 0) for updates, ("unit", u) and
    #: ("gateway", 0) for the gateway's answers
    waiting: dict[tuple[str, int], list[Fault]] = field(default_factory=lambda: defaultdict(list))
    event_log: list[str] = field(default_factory=list)
    #: slaves whose last "slave" event from the poller said offline
    offline: set[int] = field(default_factory=set)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def success(self, key: tuple[str, int], t: float) -> None:
        """A good value through `key` at wall time `t` (call with the lock held): the
        faults replugged before it on that path have recovered."""
        for k in (key, (("poller", 0) if key[0] == "slave" else ("gateway", 0))):
            faults = self.waiting.get(k)
            if faults:
                left = []
                for f in faults:
                    if f.replugged < t:
                        f.recovered = t
                    else:
                        left.append(f)
                self.waiting[k] = left


#: the path whose first good value after the replug ends each kind of fault
PATH = {"drive": "slave", "poller": "poller", "gwdrive": "unit", "gateway": "gateway"}


def rss_kb(pid: int) -> tuple[int, int]:
    """(VmRSS, VmHWM) of a process in KiB, (0, 0) once it is gone."""
    vals = {"VmRSS": 0, "VmHWM": 0}
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            k, _, v = line.partition(":")
            if k in vals:
                vals[k] = int(v.split()[0])
    return vals["VmRSS"], vals["VmHWM"]


def read_truth(port: str, slaves: list[int], baud: int) -> dict[int, dict[int, int]]:
    import pyrtu

    out: dict[int, dict[int, int]] = {}
    with pyrtu.Master(port, baudrate=baud, parity="N", timeout=0.5, retries=5) as m:
        for s in slaves:
            vals: dict[int, int] = {}
            for addr, n in KNOWN.items():
                for i, v in enumerate(m.read_holding_registers(s, addr, n)):
                    vals[addr + i] = v
            out[s] = vals
    return out


def poller_config(path: Path, port: str, baud: int, slaves: list[int]) -> None:
    lines = [
        "[defaults]",
        'bus = "P"',
        "interval = 0.05",
        "",
        "[[bus]]",
        'name = "P"',
        f'port = "{port}"',
        f"baudrate = {baud}",
        'parity = "N"',
        "timeout = 0.1",
        "",
    ]
    for s in slaves:
        for addr, n in KNOWN.items():
            for i in range(n):
                lines += [
                    "[[point]]",
                    f'name = "s{s}.r{addr + i}"',
                    f"slave = {s}",
                    'table = "holding"',
                    f"address = {addr + i}",
                    "",
                ]
    path.write_text("\n".join(lines))


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("closed by the gateway")
        buf += chunk
    return buf


def good_client(
    addr: tuple[str, int],
    units: list[int],
    known: dict[int, dict[int, int]],
    tally: Tally,
    stop: threading.Event,
    seed: int,
) -> None:
    """A well-behaved client: short read, long read, long write refused, in turn."""
    rng = random.Random(seed)
    tid = 0
    sock: socket.socket | None = None
    while not stop.is_set():
        try:
            if sock is None:
                sock = socket.create_connection(addr, timeout=3.0)
            unit = rng.choice(units)
            for pdu in (
                struct.pack(">BHH", 3, 680, 1),
                struct.pack(">BHH", 3, 100, 4),
                struct.pack(">BHHB", 16, 0, 60, 120) + bytes(120),  # long; refused
            ):
                tid = (tid + 1) & 0xFFFF
                sock.sendall(mbap(tid, unit, pdu))
                head = recv_exact(sock, 7)
                rtid, _, length, runit = struct.unpack(">HHHB", head)
                body = recv_exact(sock, length - 1)
                if rtid != tid or runit != unit:
                    with tally.lock:
                        tally.wrong.append(f"gateway answer tid {rtid}/{tid} unit {runit}/{unit}")
                    continue
                if body[0] & 0x80:
                    with tally.lock:
                        tally.gw_exceptions += 1
                    if pdu[0] == 16 and body[1] in (2, 3, 4):
                        with tally.lock:  # the device's own refusal: it answered
                            tally.success(("unit", unit), time.time())
                    elif body[1] in (0x0A, 0x0B):
                        stop.wait(0.02)  # the gateway's own answer: retry a little later
                    continue
                if pdu[0] == 3:
                    start, count = struct.unpack(">HH", pdu[1:5])
                    regs = struct.unpack(f">{count}H", body[2 : 2 + 2 * count])
                    want = tuple(known[unit][start + i] for i in range(count))
                    with tally.lock:
                        if regs != want:
                            tally.wrong.append(f"gateway unit {unit} @{start}: {regs} != {want}")
                        tally.gw_answers += 1
                        tally.success(("unit", unit), time.time())
        except ConnectionRefusedError:
            with tally.lock:
                tally.gw_refused += 1
            if sock:
                sock.close()
            sock = None
            stop.wait(0.2)
        except (OSError, ConnectionError) as e:
            if stop.is_set():
                break  # the run is over: the gateway is being stopped
            with tally.lock:
                tally.gw_errors += 1
                if len(tally.gw_error_examples) < 5:
                    tally.gw_error_examples.append(f"{time.time():.3f} {type(e).__name__}: {e}")
            if sock:
                sock.close()
            sock = None
            stop.wait(0.2)
    if sock:
        sock.close()


def abuser(
    addr: tuple[str, int], kind: str, tally: Tally, stop: threading.Event, seed: int
) -> None:
    """A client that does not talk properly; reconnects when the gateway closes it."""
    rng = random.Random(seed)
    while not stop.is_set():
        try:
            with socket.create_connection(addr, timeout=1.0) as s:
                with tally.lock:
                    tally.abuser_connects += 1
                s.settimeout(0.5)
                if kind == "half":
                    s.sendall(b"\x00\x01\x00")
                elif kind == "garbage":
                    s.sendall(rng.randbytes(rng.randint(1, 40)))
                while not stop.is_set():
                    if kind == "drip":
                        s.sendall(b"\x00")
                        if stop.wait(1.0):
                            break
                    try:
                        if s.recv(256) == b"":
                            break  # closed by the gateway
                    except TimeoutError:
                        continue
                with tally.lock:
                    tally.abuser_closed += 1
        except OSError:
            pass
        stop.wait(0.2)


def read_poller(
    proc: subprocess.Popen[str], known: dict[int, dict[int, int]], tally: Tally
) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        if "point" in obj and "value" in obj:
            s, r = obj["point"][1:].split(".r")
            slave, reg = int(s), int(r)
            with tally.lock:
                tally.updates += 1
                tally.success(("slave", slave), float(obj["time"]))
                if obj["value"] != known[slave][reg]:
                    tally.wrong.append(f"poller s{slave} r{reg}: {obj['value']}")
        else:
            kind = obj.get("event") or obj.get("type") or ("summary" if obj.get("summary") else "?")
            with tally.lock:
                if kind == "slave":
                    (tally.offline.discard if obj["online"] else tally.offline.add)(obj["slave"])
                tally.events[str(kind)] += 1
                if kind != "summary":
                    tally.event_log.append(f"{time.time():.3f} {line.strip()}")


def read_gateway(proc: subprocess.Popen[str], tally: Tally) -> None:
    """The gateway's JSON lines after "ready" (its bus events): counted, and drained so
    that its stdout never fills."""
    assert proc.stdout is not None
    for line in proc.stdout:
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        state = {True: " up", False: " down"}.get(obj.get("up"), "")
        kind = f"gateway {obj.get('type', '?')}{state}"
        with tally.lock:
            tally.events[kind] += 1


def spawn(args: list[str], **kw: Any) -> subprocess.Popen[str]:
    return subprocess.Popen(PYRTU + args, text=True, **kw)


def stop_proc(p: subprocess.Popen[str], timeout: float = 10.0) -> int | None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
            return None
    return p.returncode


def phase(baud: int, args: argparse.Namespace, out: dict[str, Any]) -> None:
    rng = random.Random(args.seed + baud)
    n = args.drives
    slaves = list(range(1, n + 1))
    gw_units = slaves[:2]
    tmp = Path(tempfile.mkdtemp(prefix=f"soak{baud}-"))
    faults = Faults(seed=args.seed, bit_flip_rate=args.bit_flip_rate)
    bus_p = VirtualBus(n + 1, baudrate=baud, parity="N", directory=str(tmp / "P"), faults=faults)
    bus_g = VirtualBus(3, baudrate=baud, parity="N", directory=str(tmp / "G"), faults=faults)
    procs: dict[str, subprocess.Popen[str]] = {}
    tally = Tally()
    stop = threading.Event()
    threads: list[threading.Thread] = []
    injected: list[Fault] = []
    try:
        bus_p.start()
        bus_g.start()
        line = ["-b", str(baud), "-P", "N"]
        for i, s in enumerate(slaves):
            ports = ["--port", bus_p.path(i)]
            if s in gw_units:
                ports += ["--port", bus_g.path(gw_units.index(s))]
            procs[f"drive{s}"] = spawn(
                ["simulate", "cfw701", "-a", str(s), "--state", "stopped", *line, *ports],
                stdout=subprocess.DEVNULL,
                stderr=open(tmp / f"drive{s}.err", "w"),
            )
        for i in range(n):
            bus_p.wait_clients(i, 1, timeout=10)
        for i in range(len(gw_units)):
            bus_g.wait_clients(i, 1, timeout=10)
        known = read_truth(bus_p.path(n), slaves, baud)
        known_g = read_truth(bus_g.path(2), gw_units, baud)
        if any(known_g[u] != known[u] for u in gw_units):
            raise SystemExit("soak: the G drives do not hold what the P drives hold")
        cfg = tmp / "soak.toml"
        poller_config(cfg, bus_p.path(n), baud, slaves)
        procs["poller"] = spawn(
            ["poll", "--config", str(cfg), "--json", "--all"],
            stdout=subprocess.PIPE,
            stderr=open(tmp / "poller.err", "w"),
        )
        threads.append(
            threading.Thread(target=read_poller, args=(procs["poller"], known, tally), daemon=True)
        )
        units = ",".join(map(str, gw_units))
        procs["gateway"] = spawn(
            [
                "gateway",
                "--listen",
                "127.0.0.1:0",
                "--port",
                f"{bus_g.path(2)}={units}",
                "--json",
                "-o",
                "0.1",
                *line,
            ],
            stdout=subprocess.PIPE,
            stderr=open(tmp / "gateway.err", "w"),
        )
        assert procs["gateway"].stdout is not None
        ready = json.loads(procs["gateway"].stdout.readline())
        host, port = ready.get("listen", "127.0.0.1:0").rsplit(":", 1)
        addr = (host, int(port))
        threads.append(
            threading.Thread(target=read_gateway, args=(procs["gateway"], tally), daemon=True)
        )
        for k in range(args.clients):
            threads.append(
                threading.Thread(
                    target=good_client, daemon=True, args=(addr, gw_units, known, tally, stop, k)
                )
            )
        kinds = ("idle", "drip", "garbage", "half")
        for k in range(args.abusers):
            threads.append(
                threading.Thread(
                    target=abuser, daemon=True, args=(addr, kinds[k % 4], tally, stop, k)
                )
            )
        for t in threads:
            t.start()
        time.sleep(args.warmup)
        mem0 = {name: rss_kb(p.pid) for name, p in procs.items()}
        targets = [("drive", s) for s in slaves] + [("poller", 0), ("gateway", 0)]
        targets += [("gwdrive", u) for u in gw_units]
        end = time.monotonic() + args.minutes * 60.0
        k = 0
        while time.monotonic() < end:
            kind, who = targets[k % len(targets)]
            k += 1
            if kind == "drive":
                bus, drop = bus_p, who - 1
            elif kind == "poller":
                bus, drop = bus_p, n
            elif kind == "gateway":
                bus, drop = bus_g, 2
            else:
                bus, drop = bus_g, gw_units.index(who)
            f = Fault(kind, who, time.time())
            bus.unplug(drop, after_bytes=rng.randint(0, 6))
            time.sleep(args.down)
            with tally.lock:
                bus.replug(drop)
                f.replugged = time.time()
                injected.append(f)
                tally.waiting[(PATH[kind], who)].append(f)
            time.sleep(args.cycle)
        deadline = time.monotonic() + RECOVER_LIMIT
        while time.monotonic() < deadline and not settle(injected, tally):
            time.sleep(0.2)
        mem1 = {name: rss_kb(p.pid) for name, p in procs.items()}
        alive = {name: p.poll() is None for name, p in procs.items()}
    finally:
        stop.set()
        # the masters first (the poller, the gateway), then the drives they poll: a
        # drive stopped first would be a slave offline at the poller's end (exit 4)
        order = sorted(procs, key=lambda name: name.startswith("drive"))
        codes = {name: stop_proc(procs[name]) for name in order}
        bus_p.close()
        bus_g.close()
    rec = [f.recovery for f in injected if f.recovery is not None]
    by_kind: dict[str, list[float]] = defaultdict(list)
    for f in injected:
        if f.recovery is not None:
            by_kind[f.kind].append(f.recovery)
    out[str(baud)] = {
        "faults_injected": len(injected),
        "faults_recovered": len(rec),
        "unrecovered": [f"{f.kind} {f.target}" for f in injected if f.recovery is None],
        "recovery_s": {
            kk: {"n": len(v), "median": sorted(v)[len(v) // 2], "max": max(v)}
            for kk, v in by_kind.items()
        },
        "slowest_recovery_s": max(rec) if rec else None,
        "wrong_values": len(tally.wrong),
        "wrong_examples": tally.wrong[:5],
        "poller_updates": tally.updates,
        "events": dict(tally.events),
        "gateway_answers": tally.gw_answers,
        "gateway_exceptions": tally.gw_exceptions,
        "good_client_errors": tally.gw_errors,
        "good_client_error_examples": tally.gw_error_examples,
        "good_client_refused": tally.gw_refused,
        "abuser_connects": tally.abuser_connects,
        "abusers_closed_by_gateway": tally.abuser_closed,
        "all_alive_at_end": alive,
        "exit_codes": codes,
        "slaves_offline_at_stop": sorted(tally.offline),
        "rss_kb_start": {kk: v[0] for kk, v in mem0.items()},
        "rss_kb_end": {kk: v[0] for kk, v in mem1.items()},
        "rss_kb_peak": {kk: v[1] for kk, v in mem1.items()},
        "bus_counters": {"P_faults": dict(bus_p.counters().faults)},
    }
    if args.keep:
        out[str(baud)]["dir"] = str(tmp)
        (tmp / "poller-events.log").write_text("\n".join(tally.event_log) + "\n")
        (tmp / "faults.log").write_text(
            "".join(
                f"{f.unplugged:.3f} {f.replugged:.3f} {f.recovered:.3f} {f.kind} {f.target}\n"
                for f in injected
            )
        )
    else:
        shutil.rmtree(tmp, ignore_errors=True)


def settle(injected: list[Fault], tally: Tally) -> bool:
    """True when every fault injected has recovered and the poller counts every slave
    online again (a slave offline at the end would make it exit 4, rightly)."""
    with tally.lock:
        return all(f.recovered for f in injected) and not tally.offline


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--bauds", default="19200,115200")
    ap.add_argument("--drives", type=int, default=8)
    ap.add_argument("--clients", type=int, default=4, help="well-behaved TCP clients")
    ap.add_argument("--abusers", type=int, default=64, help="abusive TCP clients")
    ap.add_argument("--cycle", type=float, default=4.0, help="seconds between faults")
    ap.add_argument("--down", type=float, default=1.5, help="seconds a drop stays unplugged")
    ap.add_argument("--warmup", type=float, default=3.0)
    ap.add_argument("--bit-flip-rate", type=float, default=2e-5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", help="write the report here")
    ap.add_argument("--keep", action="store_true", help="keep the run's directory and logs")
    ap.add_argument(
        "--short",
        action="store_true",
        help="the CI version: 19200 only, 3 drives, 40 s, 16 abusers",
    )
    args = ap.parse_args(argv)
    if args.short:
        args.bauds, args.drives, args.minutes, args.abusers = "19200", 3, 40 / 60, 16
        args.cycle, args.down = 2.5, 1.0
    out: dict[str, Any] = {"args": vars(args), "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    for baud in (int(b) for b in args.bauds.split(",")):
        phase(baud, args, out)
    text = json.dumps(out, indent=2, default=str)
    if args.json:
        Path(args.json).write_text(text)
    print(text)
    ok = all(
        not out[b]["unrecovered"] and out[b]["wrong_values"] == 0 for b in args.bauds.split(",")
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
