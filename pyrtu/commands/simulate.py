"""``pyrtu simulate DEVICE --port PATH``: a simulated drive on a serial port.

DEVICE is one of cfw100, cfw320, cfw701 (WEG), cv100 (CV100/FV100), act, acu
(Bonfiglioli Vectron): the simulators of `pyrtu.devices`, which answer as their
manuals say (function codes, exceptions, identification, response delay, motor
ramps, status words, serial watchdog).  ``--address`` defaults to the address of
the manual's examples.  Put it on a drop of ``pyrtu vbus`` (with ``--parity N``:
pseudo-terminals carry no parity) or on a real port.

Runs until SIGINT/SIGTERM or ``--duration`` (exit 0), then prints the counters;
``--watch`` prints the drive's frequency and status word every second.

``--port`` may be given several times: one drive per port, each with its own
state, all served by one event loop in this process (cheaper than a process per
drive when one machine simulates many buses); ``--watch`` then prints a line per
port and the counters are added up.
"""

from __future__ import annotations

import argparse
import inspect
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from ._simulate_many import DriveLoop
from ._simulate_tcp import TcpThread, tcp_only_slave
from .common import (
    EXIT_OK,
    CommandSpec,
    add_json_option,
    add_serial_options,
    describe_format,
    emit,
    exit_code_table,
    guarded,
    positive_seconds,
    serial_kwargs,
    stop_on_signals,
)
from .gateway import listen_address
from .io import DEVICES

VENDORS = {
    "cfw100": "WEG CFW100",
    "cfw320": "WEG CFW320",
    "cfw701": "WEG CFW701",
    "cv100": "CV100/FV100",
    "act": "Bonfiglioli Vectron ACT",
    "acu": "Bonfiglioli Vectron ACU",
}


def make_simulator(device: str, state: str | None = None, mode: str = "rtu") -> Any:
    """The simulator of ``device``; ``state`` where the simulator has states."""
    from ..devices import SIMULATORS, simulator

    options: dict[str, Any] = {}
    params = inspect.signature(SIMULATORS[device]).parameters
    if state is not None:
        if "state" not in params:
            raise ValueError(
                f"the {device} simulator has no --state (it starts as its manual says)"
            )
        options["state"] = state
    if mode != "rtu":
        options["mode"] = mode
    return simulator(device, **options)


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
        type=str.lower,
        choices=DEVICES,
        help="cfw100, cfw320, cfw701, cv100, act or acu",
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
        type=listen_address,
        metavar="HOST:PORT",
        help="also (or only, without --port) serve the drive over Modbus TCP",
    )
    p.add_argument(
        "-a",
        "--address",
        type=int,
        metavar="N",
        help="slave address (default: the manual's example address)",
    )
    p.add_argument(
        "--state",
        choices=["manual", "stopped"],
        help="WEG and CV100: start in the state of the manual's examples (default) or stopped",
    )
    p.add_argument(
        "-d", "--duration", type=positive_seconds, metavar="SECONDS", help="stop after this time"
    )
    p.add_argument("--watch", action="store_true", help="print frequency and status every second")
    add_json_option(p, "JSON lines: ready, status (--watch), stopped")
    add_serial_options(p, timeout=None)


def _run(args: argparse.Namespace) -> int:
    from ..devices import EXAMPLE_ADDRESS

    device: str = args.device
    address = args.address if args.address is not None else EXAMPLE_ADDRESS[device]
    if not 1 <= address <= 247:
        raise ValueError(f"--address: a slave address is 1..247, not {address}")
    ports: list[str] = args.port or []
    if not ports and args.tcp is None:
        raise ValueError("give --port PATH, --tcp HOST:PORT or both")
    if len(set(ports)) != len(ports):
        raise ValueError("--port: a port is given twice (one drive per port)")
    if len(ports) > 1 and args.tcp is not None:
        raise ValueError("--tcp serves one drive: give it with a single --port")
    args.ports = ports
    args.port = ", ".join(ports) or None  # what an error message names
    options = serial_kwargs(args)
    options.update(mode=args.mode, timing=args.timing, exclusive=args.exclusive)
    if args.t35 is not None:
        options["t35"] = args.t35
    if len(ports) > 1:
        return _run_many(args, device, address, ports, options)
    sim = make_simulator(device, args.state, args.mode)
    with stop_on_signals() as stop:  # before the "ready" line: a signal after it stops cleanly
        tcp = None
        try:
            slave = sim.serve(args.port, address, **options) if args.port else None
            if args.tcp is not None:
                app = slave if slave is not None else tcp_only_slave(sim, address)
                tcp = TcpThread(app, *args.tcp)
                args.tcp = tcp.address  # the port bound (0: any free port)
        except BaseException:
            sim.close()
            raise
        started = time.monotonic()
        try:
            _ready(args, device, address, sorted((slave or app).functions))
            _serve(args, stop, started, lambda: None if slave is None else slave.error, [sim])
        finally:
            counters = slave.counters if slave is not None else _tcp_counters(tcp)
            if tcp is not None:
                tcp.stop()
            sim.close()
    _stopped(args, time.monotonic() - started, counters)
    return EXIT_OK


def _run_many(
    args: argparse.Namespace, device: str, address: int, ports: list[str], options: dict[str, Any]
) -> int:
    """One drive per port, served by `DriveLoop` (one event loop, one thread)."""
    sims: list[Any] = []
    slaves: list[Any] = []
    with stop_on_signals() as stop:
        try:
            for port in ports:
                sims.append(make_simulator(device, args.state, args.mode))
                slaves.append(sims[-1].make_async_slave(port, address, **options))
            drives = DriveLoop(slaves)
            drives.start()
        except BaseException:
            for slave in slaves:
                slave.port.close()
            raise
        started = time.monotonic()
        try:
            _ready(args, device, address, sorted(slaves[0].functions))
            _serve(args, stop, started, lambda: drives.error, sims, ports)
        finally:
            drives.stop()
    _stopped(args, time.monotonic() - started, drives.counters)
    return EXIT_OK


def _serve(
    args: argparse.Namespace,
    stop: threading.Event,
    started: float,
    error: Callable[[], BaseException | None],
    sims: list[Any],
    ports: list[str] | None = None,
) -> None:
    """Until a signal or ``--duration``: raise the error that ended a drive's slave,
    print the ``--watch`` lines (one per drive; with ``ports``, each names its port)."""
    deadline = None if args.duration is None else started + args.duration
    next_watch = started + 1.0
    while not stop.is_set():
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            break
        exc = error()
        if exc is not None:
            raise exc
        if args.watch and now >= next_watch:
            next_watch += 1.0
            for i, sim in enumerate(sims):
                _watch(args, sim, now - started, None if ports is None else ports[i])
        wake = min(next_watch if args.watch else now + 0.2, now + 0.2)
        if deadline is not None:
            wake = min(wake, deadline)
        stop.wait(max(0.0, wake - now))


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


def _ready(args: argparse.Namespace, device: str, address: int, functions: list[int]) -> None:
    tcp = None if args.tcp is None else f"{args.tcp[0]}:{args.tcp[1]}"
    if args.json:
        emit(
            {
                "type": "ready",
                "device": device,
                "address": address,
                "port": args.ports[0] if args.ports else None,
                "ports": args.ports,
                "tcp": tcp,
                "format": f"{describe_format(args)} {args.mode.upper()}",
                "functions": functions,
            }
        )
    else:
        where = f"on {args.port}, " if args.port else ""
        where += f"Modbus TCP on {tcp}, " if tcp else ""
        print(
            f"pyrtu simulate: {VENDORS[device]} at address {address} {where}"
            f"{describe_format(args)} {args.mode.upper()} "
            f"(functions {', '.join(map(str, functions))}); Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )


def _watch(args: argparse.Namespace, sim: Any, t: float, port: str | None = None) -> None:
    hz, text = frequency_of(sim), status_of(sim)
    if args.json:
        line: dict[str, Any] = {"type": "status", "t": round(t, 3)}
        line.update({"port": port} if port is not None else {})
        emit({**line, "frequency_hz": round(hz, 3), "status": text})
    else:
        where = f"{port}  " if port is not None else ""
        print(f"{t:7.1f} s  {where}{hz:7.2f} Hz  {text}", flush=True)


COMMANDS = (
    CommandSpec(
        "simulate",
        "run a simulated drive (cfw100, cfw320, cfw701, cv100, act, acu) on a port",
        _configure,
        guarded("simulate", _run),
        (__doc__ or "").strip() + "\n\n" + exit_code_table(),
    ),
)
