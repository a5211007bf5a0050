"""``pyrtu simulate DEVICE --port PATH``: a simulated device on a serial port.

DEVICE is a device template of the registry (``pyrtu template list``).  The drives
of the manuals, cfw100, cfw320, cfw701 (WEG), cv100 (CV100/FV100), act, acu
(Bonfiglioli Vectron), have simulators of `pyrtu.devices`, which answer as their
manuals say (function codes, exceptions, identification, response delay, motor
ramps, status words, serial watchdog).  Any other template, or ``--template FILE``
(a ``.toml`` file), is served from its points: their initial values (the
template's ``initial``, or ``--values FILE``: ``point = value`` lines), writes
checked against ``writable``, ``min`` and ``max`` (exception 2 for a point that is
not writable or an address no point covers, 3 for a value out of range), the
template's identity on FC 43 (docs/TEMPLATES.md).  ``--address`` defaults to the
template's ``address`` (the manual's examples').  Put it on a drop of ``pyrtu vbus``
(with ``--parity N``:
pseudo-terminals carry no parity) or on a real port.

``--vary SECONDS`` makes a template's values change: every SECONDS (from the
start), each point no client can write (a measured value: not ``writable``, or
in the input registers or discrete inputs) takes the next step of a ramp, the
same on every device: a number goes up by one count of its register (``scale``
in its units) and wraps from the top of its ``min``..``max`` (else of what its
register holds) to the bottom; a bool toggles; an enum takes its next value; a
string keeps its value.  With ``--tcp HOST:FIRST-LAST`` every device of the range
steps at the same instants (``pyrtu.cli._simulate_template``).  The drives of the
manuals compute their values: ``--vary`` with one of them is a usage error, as is
a time that is not above 0 (exit 2, naming ``--vary``, before a port opens).

Runs until SIGINT/SIGTERM or ``--duration``, then prints the counters;
``--watch`` prints the drive's frequency and status word every second.

``--port`` may be given several times: one drive per port, each with its own
state, all served by one event loop in this process (cheaper than a process per
drive when one machine simulates many buses); ``--watch`` then prints a line per
port and the counters are added up.  A port given twice (also as ``./P`` and
``P``, or a symlink and its target) is a usage error (exit 2).

A port that cannot be opened at the start is an error (exit 3: a wrong path is
said at once).  A port that fails while served (a USB adapter pulled, a
virtual-bus drop unplugged) is reported once (one line on stderr; ``--json``:
a "port_lost" line), tried again with growing waits (0.5 s doubling to 30 s) and
served again when it opens ("port_back"); the drive keeps its state and the
other drives carry on meanwhile.  The exit status after SIGINT/SIGTERM or
``--duration`` is 0 when every port is served at the end, 3 when a port was still
down (each named on stderr).

Every background part is supervised.  With ``--tcp``, the TCP server's tasks are
restarted on the back-off when they raise (one line on stderr, "task_failed" in
``--json``; the requests wait meanwhile).  The thread of the TCP server or of the
drives' event loop ending while it should serve (nothing is left to answer) ends
the command at once: one line naming it and its cause ("internal error" in
``--json``) and exit status 1 (an internal error: the failure is the program's,
not a port's, so not 3).

``--tcp HOST:FIRST-LAST`` (``--tcp 127.0.0.1:20000-20999``) serves a device on
every port of the range, each with its own state (as ``--port`` given many
times), all from one event loop with one listening socket per port: a thousand
Modbus TCP devices for the price of one process (docs/many-devices.md).  A range
takes no ``--port``; one that ends before it starts, holds port 0 or more than
10,000 ports is a usage error (exit 2, naming ``--tcp``); a port of it that
cannot be bound is a port error (exit 3, naming the port).  The soft limit of
open files is raised to a socket per port and per client where the hard limit
allows (else exit 2).  The counters, ``--watch`` and ``--metrics`` add up the
ports'.

``--udp HOST:PORT`` serves the drive over Modbus over UDP (one MBAP ADU per
datagram, as pymodbus's ``ModbusUdpClient`` and Home Assistant's ``type: udp``
send it), beside ``--tcp`` or alone; a datagram that is not one whole Modbus ADU is
dropped and counted.

With ``--tcp`` or ``--udp``, ``--policy FILE``, ``--read-only`` and ``--audit
FILE|-`` guard the listeners as they guard ``pyrtu gateway``'s (docs/security.md;
a UDP client's identity is the address its datagrams come from).

With ``--metrics HOST:PORT``: Prometheus metrics on /metrics (the drives'
counters, each port's state, with ``--tcp`` the connected clients) and a health
check on /healthz (docs/METRICS.md).

Two simulators (or devices) answering one address on one bus garble each
other's answers: a simulator that hears bytes on the line while it answers, or
an answer at its own address that it did not send, warns once on stderr
("warning" in ``--json``) and goes on serving.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

from pyrtu.cli._security import add_security_options, open_security
from pyrtu.cli._simulate_clash import watch_slave
from pyrtu.cli._simulate_many import DriveLoop, DriveThread, PortKeeper, PortReport
from pyrtu.cli._simulate_tcp import TcpThread, open_files_for, tcp_only_slave, tcp_range
from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_FAILURE,
    EXIT_OK,
    EXIT_PORT,
    add_duration_option,
    add_json_option,
    add_seconds_option,
    add_serial_options,
    describe_format,
    emit,
    serial_kwargs,
    stop_on_signals,
)
from pyrtu.cli.gateway import listen_address
from pyrtu.cli.template import template_name
from pyrtu.drivers._portname import first_duplicate
from pyrtu.drivers.supervise import TaskFailure, cause
from pyrtu.metrics.address import add_metrics_option, open_metrics


def find_device(args: argparse.Namespace) -> Any:
    """The template DEVICE or ``--template`` names (ValueError: usage)."""
    from pyrtu.devices.registry import TemplateError, find_template

    if (args.device is None) == (args.template is None):
        both = args.device is not None
        raise ValueError(
            "give DEVICE (pyrtu template list) or --template FILE, not both"
            if both
            else "give DEVICE (pyrtu template list) or --template FILE"
        )
    try:
        return find_template(args.device if args.device is not None else args.template)
    except TemplateError as e:
        what = "DEVICE" if args.device is not None else "--template"
        raise ValueError(f"{what}: {e}") from None


def make_simulator(
    device: Any,
    state: str | None = None,
    mode: str = "rtu",
    values: Any = None,
    vary: float | None = None,
) -> Any:
    """The simulator of template ``device`` (a `Template`, or a registry name): its
    drive simulator where it has one (``state`` where that has states), else a
    `TemplateSimulator` with ``values`` (``vary``: its measured values step every
    ``vary`` seconds)."""
    from pyrtu.devices.registry import find_template

    template = find_template(device) if isinstance(device, str) else device
    cls = template.hook("simulator")
    if cls is None:
        if state is not None:
            raise ValueError(f"--state: the {template.name} template has no states")
        from pyrtu.cli._simulate_template import TemplateSimulator

        return TemplateSimulator(template, values, mode=mode, vary=vary)
    for flag, given in (("--values", values), ("--vary", vary)):
        if given is not None:
            raise ValueError(f"{flag}: the {template.name} simulator computes its values")
    options: dict[str, Any] = {}
    params = inspect.signature(cls).parameters
    if state is not None:
        if "state" not in params:
            raise ValueError(
                f"the {template.name} simulator has no --state (it starts as its manual says)"
            )
        options["state"] = state
    if mode != "rtu":
        options["mode"] = mode
    return cls(**options)


def _watch_text(sim: Any) -> str | None:
    describe = getattr(sim, "describe", None)
    return str(describe()) if callable(describe) else None


def frequency_of(sim: Any) -> float:
    reader = getattr(sim, "frequency_hz", None) or sim.speed_hz
    value: float = reader()
    return value


def status_of(sim: Any) -> str:
    status = sim.status()
    describe = getattr(status, "describe", None)
    return str(describe() if describe is not None else status)


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "device",
        metavar="DEVICE",
        nargs="?",
        type=template_name,
        help="a device template: cfw100, cfw320, cfw701, cv100, act, acu or any of "
        "pyrtu template list",
    )
    p.add_argument(
        "--template",
        metavar="FILE",
        help="serve this device template (a .toml file) instead of DEVICE",
    )
    p.add_argument(
        "--values",
        metavar="FILE",
        help="initial values of the template's points (TOML: point = value)",
    )
    p.add_argument(
        "-p",
        "--port",
        metavar="PATH",
        action="append",
        help="serial port to serve; give it again for one more drive (one per port)",
    )
    p.add_argument(
        "--tcp",
        type=tcp_range,
        metavar="HOST:PORT",
        help="also (or only, without --port) serve the drive over Modbus TCP; "
        "HOST:FIRST-LAST: a device on every port of the range (without --port)",
    )
    p.add_argument(
        "--udp",
        type=listen_address,
        metavar="HOST:PORT",
        help="also (or only) serve the drive over Modbus over UDP (one MBAP ADU per "
        "datagram, as pymodbus's UDP client sends); the client's address is its identity "
        "for --policy",
    )
    p.add_argument(
        "-a",
        "--address",
        type=int,
        metavar="N",
        help="slave address (default: the template's, the manual's example address)",
    )
    p.add_argument(
        "--state",
        choices=["manual", "stopped"],
        help="WEG and CV100: start in the state of the manual's examples (default) or stopped",
    )
    add_seconds_option(
        p,
        "--vary",
        default=None,
        help="every SECONDS, each measured value (a point no client can write) takes the "
        "next step of its ramp within its min..max (templates, not the drives' simulators)",
    )
    add_duration_option(p)
    p.add_argument("--watch", action="store_true", help="print frequency and status every second")
    add_json_option(p, "JSON lines: ready, status (--watch), stopped")
    add_serial_options(p, timeout=None)
    add_metrics_option(p)
    add_security_options(p, listen_address)


def _run_metered(args: argparse.Namespace) -> int:
    """`_run`, with ``--metrics`` bound before any port opens and closed after."""
    args.metrics_server = open_metrics(args.metrics, "simulate")
    try:
        return _run(args)
    finally:
        if args.metrics_server is not None:
            args.metrics_server.close()


def _serve_metrics(
    args: argparse.Namespace, counters: Any, keeper: Any, tcp: Any, watched: Any
) -> None:
    """Answer ``--metrics`` from now on (docs/METRICS.md)."""
    if args.metrics_server is not None:
        from pyrtu.metrics.simulate import SimulateSource

        down = keeper.down if keeper is not None else list
        source = SimulateSource(counters, args.ports, down, tcp, watched)
        args.metrics_server.serve(source)


def _run(args: argparse.Namespace) -> int:
    template = find_device(args)
    device: str = template.name
    address = args.address if args.address is not None else template.address
    if not 1 <= address <= 247:
        raise ValueError(f"--address: a slave address is 1..247, not {address}")
    ports: list[str] = args.port or []
    if not ports and args.tcp is None and args.udp is None:
        raise ValueError("give --port PATH, --tcp HOST:PORT, --udp HOST:PORT or several")
    twice = first_duplicate(ports)
    if twice is not None:
        a, b = ports[twice[0]], ports[twice[1]]
        same = f"{a} is given twice" if a == b else f"{a} and {b} are one port"
        raise ValueError(f"--port: {same} (one drive per port: give each port once)")
    tcp_ports = [] if args.tcp is None else list(range(args.tcp[1], args.tcp[2] + 1))
    if len(tcp_ports) > 1 and ports:
        raise ValueError(
            "--tcp: a range of ports serves a device of its own on each port: give no --port"
        )
    for flag, given in (("--tcp", args.tcp), ("--udp", args.udp)):
        if len(ports) > 1 and given is not None:
            raise ValueError(f"{flag} serves one drive: give it with a single --port")
    if len(tcp_ports) > 1 and args.udp is not None:
        raise ValueError("--udp serves one device: give --tcp a single HOST:PORT")
    if len(tcp_ports) > 1:
        open_files_for(len(tcp_ports))
    if args.tcp is None and args.udp is None and (args.policy or args.read_only or args.audit):
        raise ValueError(
            "--policy, --read-only and --audit go with --tcp or --udp: give --tcp HOST:PORT"
        )
    if args.tcp is None and args.tls_listen:
        raise ValueError("--tls-listen goes with --tcp: give --tcp HOST:PORT")
    if len(tcp_ports) > 1 and args.tls_listen:
        raise ValueError("--tls-listen serves one device: give --tcp a single HOST:PORT")
    security = open_security(args, "simulate")  # exit 2 on a bad policy, before a port opens
    args.ports = ports
    args.port = ", ".join(ports) or None  # what an error message names
    options = serial_kwargs(args)
    options.update(mode=args.mode, timing=args.timing, exclusive=args.exclusive)
    if args.t35 is not None:
        options["t35"] = args.t35
    values = None
    for flag, given in (("--values", args.values), ("--vary", args.vary)):
        if given is not None and template.hook("simulator") is not None:
            raise ValueError(f"{flag}: the {device} simulator computes its values")
    if args.values is not None:
        from pyrtu.cli._simulate_template import read_values
        from pyrtu.poller.config import template_points

        values = read_values(args.values, template_points(template)[0])
    args.values_of = values
    args.title = template.description or template.title
    if len(ports) > 1:
        return _run_many(args, template, address, ports, options)
    if len(tcp_ports) > 1:
        return _run_tcp_range(args, template, address, tcp_ports, security)
    sim = make_simulator(template, args.state, args.mode, values, args.vary)
    with stop_on_signals() as stop:  # before the "ready" line: a signal after it stops cleanly
        tcp = None
        drive = None
        try:
            if ports:
                drive = DriveThread(lambda: _watched(args, sim.serve(ports[0], address, **options)))
            if args.tcp is not None or args.udp is not None:
                app = drive.slave if drive is not None else tcp_only_slave(sim, address)
                host, port, _ = args.tcp or (args.udp[0], None, None)
                tcp = TcpThread(app, host, port, on_task=lambda f: _task_failed(args, f),
                                tls=security.tls, udp=args.udp,
                                **security.server_kwargs())  # fmt: skip
                if tcp.address is not None:  # the port bound (0: any free port)
                    args.tcp = (*tcp.address, tcp.address[1])
                args.tls_bound = tcp.server.tls_address
                args.udp_bound = tcp.server.udp_address
                security.warn_if_open([tcp.address, args.tls_bound, args.udp_bound])
        except BaseException:
            sim.close()
            raise
        started = time.monotonic()
        keeper = PortKeeper(drive, ports) if drive is not None else None
        try:
            functions = drive.slave.functions if drive is not None else app.functions
            _ready(args, device, address, sorted(functions))
            watched = [] if tcp is None else [("the TCP server", tcp)]
            serial = (lambda: drive.counters) if drive is not None else None
            _serve_metrics(args, serial, keeper, tcp, watched)
            died = _serve(args, stop, started, keeper, [sim], watched=watched)
        finally:
            counters = drive.counters if drive is not None else _tcp_counters(tcp)
            if tcp is not None:
                tcp.stop()
            sim.close()
    _stopped(args, time.monotonic() - started, counters)
    return _died(args, died) if died else _still_down(args, keeper)


def _run_many(
    args: argparse.Namespace, template: Any, address: int, ports: list[str], options: dict[str, Any]
) -> int:
    """One drive per port, served by `DriveLoop` (one event loop, one thread)."""
    device: str = template.name
    sims = [
        make_simulator(template, args.state, args.mode, args.values_of, args.vary) for _ in ports
    ]
    with stop_on_signals() as stop:
        drives = DriveLoop(
            lambda i: sims[i].make_async_slave(ports[i], address, **options), len(ports)
        )
        drives.start()
        started = time.monotonic()
        keeper = PortKeeper(drives, ports)
        try:
            _ready(args, device, address, sorted(drives.slaves[0].functions))
            watched = [("the drives' event loop", drives)]
            _serve_metrics(args, lambda: drives.counters, keeper, None, watched)
            died = _serve(args, stop, started, keeper, sims, ports, watched)
        finally:
            drives.stop()
    _stopped(args, time.monotonic() - started, drives.counters)
    return _died(args, died) if died else _still_down(args, keeper)


def _run_tcp_range(
    args: argparse.Namespace,
    template: Any,
    address: int,
    tcp_ports: list[int],
    security: Any,
) -> int:
    """``--tcp HOST:FIRST-LAST``: a device per port (its own simulator), one
    `TcpServer` per port, all on one event loop (`TcpThread.many`)."""
    device: str = template.name
    host = args.tcp[0]
    sims: list[Any] = []
    with stop_on_signals() as stop:
        try:
            for _ in tcp_ports:
                sims.append(
                    make_simulator(template, args.state, args.mode, args.values_of, args.vary)
                )
            apps = [tcp_only_slave(sim, address) for sim in sims]
            tcp = TcpThread.many(apps, host, tcp_ports, on_task=lambda f: _task_failed(args, f),
                                 **security.server_kwargs())  # fmt: skip
            security.warn_if_open([tcp.address])
        except BaseException:
            for sim in sims:
                sim.close()
            raise
        started = time.monotonic()
        try:
            _ready(args, device, address, sorted(apps[0].functions))
            watched = [("the TCP server", tcp)]
            _serve_metrics(args, None, None, tcp, watched)
            where = [f"{host}:{port}" for port in tcp_ports]
            died = _serve(args, stop, started, None, sims, where, watched)
        finally:
            counters = _tcp_counters(tcp)
            tcp.stop()
            for sim in sims:
                sim.close()
    _stopped(args, time.monotonic() - started, counters)
    return _died(args, died) if died else EXIT_OK


def _serve(
    args: argparse.Namespace,
    stop: threading.Event,
    started: float,
    keeper: PortKeeper | None,
    sims: list[Any],
    ports: list[str] | None = None,
    watched: Sequence[tuple[str, Any]] = (),
) -> str | None:
    """Until a signal or ``--duration``: keep the ports served (``keeper``: a failed
    port is reported once and reopened when it is back), print the ``--watch`` lines
    (one per drive; with ``ports``, each names its port).  Ends early, saying why,
    when a thread of ``watched`` (what it is, an object with ``failure``) died."""
    deadline = None if args.duration is None else started + args.duration
    next_watch = started + 1.0
    while not stop.is_set():
        for what, thread in watched:
            if thread.failure is not None:
                return f"{what} stopped: {cause(thread.failure)}"
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            break
        if keeper is not None:
            for report in keeper.step(now):
                _port_report(args, report)
        if args.watch and now >= next_watch:
            next_watch += 1.0
            for i, sim in enumerate(sims):
                _watch(args, sim, now - started, None if ports is None else ports[i])
        wake = min(next_watch if args.watch else now + 0.2, now + 0.2)
        retry = keeper.wait(now) if keeper is not None else None
        if retry is not None:
            wake = min(wake, now + retry)
        if deadline is not None:
            wake = min(wake, deadline)
        stop.wait(max(0.0, wake - now))
    return None


def _task_failed(args: argparse.Namespace, failure: TaskFailure) -> None:
    """A task of the TCP server raised (restarted on the back-off): one line on
    stderr, a JSON event."""
    text = f"task {failure.task} failed: {failure.cause} (restarting in {failure.retry_in:.2f} s)"
    print(f"pyrtu simulate: {text}", file=sys.stderr, flush=True)
    if args.json:
        emit({"type": "task_failed", "task": failure.task, "error": failure.cause,
              "retry_in": round(failure.retry_in, 3)})  # fmt: skip


def _died(args: argparse.Namespace, why: str) -> int:
    """A thread that serves died: one line, exit status 1 (an internal error)."""
    message = f"{why}; nothing answers any more"
    print(f"pyrtu simulate: internal error: {message}", file=sys.stderr, flush=True)
    if args.json:
        emit({"ok": False, "error": "failure", "exit_code": EXIT_FAILURE, "message": message})
    return EXIT_FAILURE


def _watched(args: argparse.Namespace, slave: Any) -> Any:
    """``slave`` with a `ClashWatch`: a warning when another device answers at its address."""
    port = slave.port.name

    def warn(text: str) -> None:
        print(f"pyrtu simulate: warning: {port}: {text}", file=sys.stderr, flush=True)
        if args.json:
            emit({"type": "warning", "port": port, "message": text})

    watch_slave(slave, warn)
    return slave


def _port_report(args: argparse.Namespace, report: PortReport) -> None:
    """A port lost (once per outage) or back: one line on stderr, a JSON event."""
    error = report.error.removeprefix(f"{report.port}: ")
    if report.kind == "lost":
        text = (
            f"{report.port}: port lost: {error}; reopening it when it is back "
            "(retries with back-off), the other drives carry on"
        )
        doc: dict[str, Any] = {"type": "port_lost", "port": report.port, "error": error}
    else:
        outage = report.outage
        seconds = outage.duration if outage is not None and outage.duration is not None else 0.0
        attempts = outage.attempts if outage is not None else 0
        text = f"{report.port}: port back after {seconds:.1f} s ({attempts} failed attempts)"
        doc = {"type": "port_back", "port": report.port, "seconds": round(seconds, 3)}
        doc["attempts"] = attempts
    print(f"pyrtu simulate: {text}", file=sys.stderr, flush=True)
    if args.json:
        emit(doc)


def _still_down(args: argparse.Namespace, keeper: PortKeeper | None) -> int:
    """Exit 0, or 3 when a port was still down at the end (named, with its error)."""
    down = keeper.down() if keeper is not None else []
    if not down:
        return EXIT_OK
    now = time.monotonic()
    for port, outage in down:
        message = (
            f"{port}: still down at the end, for {now - outage.since:.1f} s"
            f" ({outage.attempts} attempts to reopen it): {outage.error.removeprefix(port + ': ')}"
        )
        print(f"pyrtu simulate: port error: {message}", file=sys.stderr)
        if args.json:
            emit({"ok": False, "error": "port", "exit_code": EXIT_PORT, "message": message})
    return EXIT_PORT


def _stopped(args: argparse.Namespace, elapsed: float, counters: dict[str, int]) -> None:
    if args.json:
        emit({"type": "stopped", "seconds": round(elapsed, 3), "counters": counters})
    else:
        print(
            f"pyrtu simulate: stopped after {elapsed:.1f} s: {counters['requests']} requests, "
            f"{counters['responses']} responses, {counters['exceptions']} exceptions",
            file=sys.stderr,
        )


def _tcp_counters(tcp: Any) -> dict[str, int]:
    c = tcp.server.counters if tcp is not None else {}
    return {
        "requests": c.get("requests", 0),
        "responses": c.get("answers", 0),
        "exceptions": c.get("exceptions", 0),
    }


def _tcp_text(listen: tuple[str, int, int]) -> str:
    """``--tcp`` for people: HOST:PORT or HOST:FIRST-LAST (``[...]`` around IPv6)."""
    host, first, last = listen
    host = f"[{host}]" if ":" in host else host
    return f"{host}:{first}" if first == last else f"{host}:{first}-{last}"


def _ready(args: argparse.Namespace, device: str, address: int, functions: list[int]) -> None:
    tcp = None if args.tcp is None else _tcp_text(args.tcp)
    # the serial format only where there is a serial port (--tcp alone has none)
    fmt = f"{describe_format(args)} {args.mode.upper()}" if args.ports else None
    tls = getattr(args, "tls_bound", None)
    also = {} if tls is None else {"tls": "{}:{}".format(*tls)}  # --tls-listen
    udp = getattr(args, "udp_bound", None)
    also.update({} if udp is None else {"udp": _tcp_text((*udp, udp[1]))})  # --udp
    if args.json:
        emit(
            {
                "type": "ready",
                "device": device,
                "address": address,
                "port": args.ports[0] if args.ports else None,
                "ports": args.ports,
                "tcp": tcp,
                "tcp_ports": 0 if args.tcp is None else args.tcp[2] - args.tcp[1] + 1,
                **also,
                "format": fmt,
                "functions": functions,
            }
        )
    else:
        where = [f" on {args.port}, {fmt}"] if fmt else [""]
        where += [f"Modbus TCP on {tcp}"] if tcp else []
        where += [f"Modbus/TCP Security on {also['tls']}"] if "tls" in also else []
        where += [f"Modbus over UDP on {also['udp']}"] if "udp" in also else []
        print(
            f"pyrtu simulate: {args.title} at address {address}{', '.join(where)} "
            f"(functions {', '.join(map(str, functions))}); Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )


def _watch(args: argparse.Namespace, sim: Any, t: float, port: str | None = None) -> None:
    text = _watch_text(sim)
    if text is not None:  # a template's points
        if args.json:
            head: dict[str, Any] = {"type": "status", "t": round(t, 3)}
            head.update({"port": port} if port is not None else {})
            emit({**head, "values": sim.values()})
        else:
            where = f"{port}  " if port is not None else ""
            print(f"{t:7.1f} s  {where}{text}", flush=True)
        return
    hz, text = frequency_of(sim), status_of(sim)
    if args.json:
        line: dict[str, Any] = {"type": "status", "t": round(t, 3)}
        line.update({"port": port} if port is not None else {})
        emit({**line, "frequency_hz": round(hz, 3), "status": text})
    else:
        where = f"{port}  " if port is not None else ""
        print(f"{t:7.1f} s  {where}{hz:7.2f} Hz  {text}", flush=True)


COMMANDS = (
    subcommand(
        "simulate",
        "run a simulated device (a template: cfw701, ..., or --template FILE) on a port",
        _configure,
        _run_metered,
        __doc__,
    ),
)
