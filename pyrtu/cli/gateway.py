"""``pyrtu gateway --listen HOST:PORT --port SERIAL[=UNITS] ...``: Modbus TCP to RTU.

Many Modbus TCP clients share the serial buses behind one listener (and, with
--listen-rtu, clients speaking RTU over TCP on a second one; with --udp-listen,
Modbus over UDP clients, one ADU per datagram): one
transaction at a time per bus at full wire rate (t3.5 between frames, no fixed
pause), a fair queue per bus (connections served in turn), the unit id as the
slave address.  ``--port`` may be repeated, each with the unit ids it carries
(``--port /dev/ttyUSB0=1-10 --port /dev/ttyUSB1=11-20,30``; one ``--port``
without ``=`` carries 1-247); ``--port tcp://HOST:PORT=UNITS`` forwards to
another Modbus TCP server, ``--port mbaps://HOST[:802]=UNITS`` to a Modbus/TCP
Security one (with --port-tls-cert, --port-tls-key, --port-tls-ca), ``--port
udp://HOST:PORT=UNITS`` to a Modbus over UDP one.  All serial
buses share the serial options.

Answers of the gateway itself (Application Protocol 7): exception 0x0A for a
unit id no bus carries, 0x0B when the device does not answer within --timeout
(after --retries), 0x06 (busy) when a queue is full.  Unit 0 is a broadcast:
sent to every bus, not answered, and the bus keeps --broadcast-delay (0.1 s)
of silence after it (the devices' turnaround).  --unit-map TCP=SLAVE sends a
TCP unit id no --port carries to a slave address: ``--unit-map 255=1,0=1`` for
clients that address a TCP device with 0xFF or 0 (Messaging on TCP/IP
Implementation Guide 4.4.1.2; libmodbus's default is 0xFF); a mapped 0 is then
answered, not broadcast.  A malformed MBAP header closes that connection (reset
after 5 s if it leaves answers unread).  Limits (defaults): --max-connections
64, --max-queue 16 requests waiting per connection, --max-bus-queue 256 per bus,
--max-write-buffer 262144 bytes of unread answers before a client is reset,
--header-timeout 5 s for a request begun to be complete, --idle-timeout 120 s
without a request; when the connections are all taken, one that never sent a
whole request (else the longest idle) gives way to the newcomer.

A bus whose port fails (a USB adapter pulled out, a TCP server gone), or is not
there at start-up (an adapter that appears after boot), is logged once; its
requests get 0x0A while it is down (counted as "bus unavailable"); it is
(re)opened on a back-off schedule (0.5 s doubling to 30 s) while the other
buses carry on, and logged again when it is back.

Runs until SIGINT/SIGTERM or --duration (exit 0), then prints the counters.
With --metrics HOST:PORT: Prometheus metrics on /metrics and a health check on
/healthz (docs/METRICS.md).

Access (docs/security.md): --policy FILE says which clients may use which units,
functions and addresses (any other request: exception 01, counted, one line per
client and reason); --read-only refuses every write; --audit FILE|- records every
executed write as a JSON line.  Listening beyond loopback with no policy is said
once at the start.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import time
from dataclasses import dataclass
from typing import Any

from pyrtu import gateway as gateways
from pyrtu.cli._security import add_security_options, open_security
from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    BUSY_ADVICE,
    EXIT_OK,
    add_duration_option,
    add_json_option,
    add_serial_options,
    emit,
    seconds,
    serial_kwargs,
    stop_when_stdout_closes,
)
from pyrtu.drivers.links import transport_of
from pyrtu.drivers.supervise import TaskFailure
from pyrtu.metrics.address import add_metrics_option, open_metrics
from pyrtu.pdu.errors import PortBusyError

#: up to this many connections the gateway runs on `pyrtu.drivers.aio.run`'s select() loop
#: (microsecond timers: the serial side keeps t3.5 to the microsecond, where the
#: default epoll loop rounds every wait up to a millisecond, a large part of a
#: 115200-baud transaction); select() takes descriptors below 1024, so beyond this
#: the default loop serves
SELECT_LOOP_CONNECTIONS = 900

#: the silence kept after a broadcast (the Serial Line spec's turnaround delay, 2.1:
#: "typically 100 ms to 200 ms"): `pyrtu.drivers.aio.AsyncMaster`'s default
BROADCAST_DELAY = 0.1


@dataclass(frozen=True)
class BusSpec:
    port: str
    units: frozenset[int] | None  # None: 1-247


def listen_address(text: str) -> tuple[str, int]:
    """HOST:PORT (``[::1]:502`` for IPv6)."""
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT (port 0..65535), not {text!r}")
    return host, int(port)


def bus_spec(text: str) -> BusSpec:
    """SERIAL or SERIAL=UNITS (unit ids ``1-10,20``); a URL its transport cannot open
    (``udp://`` without a host...) is refused here, before anything opens."""
    port, sep, units = text.rpartition("=")
    if not sep:
        port, units = text, ""
    elif not port:
        raise argparse.ArgumentTypeError(f"expected SERIAL=UNITS, not {text!r}")
    try:
        transport_of(port).check_port(port)
        return BusSpec(port, gateways.parse_units(units) if sep else None)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def unit_map(text: str) -> dict[int, int]:
    """``TCP=SLAVE[,TCP=SLAVE...]``: TCP unit ids 0..255 to slave addresses 1..247."""
    pairs: dict[int, int] = {}
    for part in text.split(","):
        unit_text, sep, slave_text = part.strip().partition("=")
        try:
            unit, slave = int(unit_text, 0), int(slave_text, 0)
        except ValueError:
            unit = slave = -1
        if not sep or not 0 <= unit <= 255 or not 1 <= slave <= 247:
            raise argparse.ArgumentTypeError(
                f"expected TCP=SLAVE (unit id 0..255 = slave address 1..247), not {part!r}"
            )
        pairs[unit] = slave
    return pairs


def seconds_or_off(text: str) -> float:
    value = seconds(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a time >= 0 (0: no limit), not {text!r}")
    return value


def _limit(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, not {text!r}")
    return value


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-l", "--listen", type=listen_address, metavar="HOST:PORT",
        help="address to listen on for Modbus TCP clients (port 0: any free port); "
        "leave it out for a gateway with only --tls-listen (or --listen-rtu, --udp-listen)",
    )  # fmt: skip
    p.add_argument(
        "--listen-rtu", type=listen_address, metavar="HOST:PORT",
        help="also listen for RTU over TCP (RTU frames with their CRC, no MBAP header)",
    )  # fmt: skip
    p.add_argument(
        "--udp-listen", type=listen_address, metavar="HOST:PORT",
        help="also listen for Modbus over UDP (one MBAP ADU per datagram; the client's "
        "address is its identity for --policy)",
    )  # fmt: skip
    p.add_argument(
        "-p", "--port", required=True, action="append", type=bus_spec, metavar="SERIAL[=UNITS]",
        help="a bus: serial port (or tcp://HOST:PORT) and its unit ids; repeat for more",
    )  # fmt: skip
    g = p.add_argument_group("limits")
    g.add_argument("--max-connections", type=_limit, default=gateways.MAX_CONNECTIONS, metavar="N",
                   help=f"TCP connections at once (default {gateways.MAX_CONNECTIONS}). Up to "
                        f"{SELECT_LOOP_CONNECTIONS} the gateway runs on a select() loop, "
                        "whose timers keep t3.5 to the microsecond; above, on asyncio's "
                        "default loop, whose timers round up to milliseconds")  # fmt: skip
    g.add_argument("--max-queue", type=_limit, default=gateways.MAX_QUEUED_PER_CONNECTION,
                   metavar="N",
                   help="requests waiting per connection "
                   f"(default {gateways.MAX_QUEUED_PER_CONNECTION})")  # fmt: skip
    g.add_argument("--max-bus-queue", type=_limit, default=gateways.MAX_QUEUED_PER_BUS,
                   metavar="N",
                   help="requests waiting per bus "
                   f"(default {gateways.MAX_QUEUED_PER_BUS})")  # fmt: skip
    g.add_argument("--max-write-buffer", type=_limit, default=gateways.MAX_WRITE_BUFFER,
                   metavar="BYTES",
                   help=f"unread answers before a client is closed "
                   f"(default {gateways.MAX_WRITE_BUFFER})")  # fmt: skip
    g.add_argument("--header-timeout", type=seconds_or_off, default=gateways.HEADER_TIMEOUT,
                   metavar="SECONDS", help="a request begun must be complete within this "
                   f"(0: no limit; default {gateways.HEADER_TIMEOUT:g})")  # fmt: skip
    g.add_argument("--idle-timeout", type=seconds_or_off, default=gateways.IDLE_TIMEOUT,
                   metavar="SECONDS", help="close a connection without a request for this "
                   f"long (0: no limit; default {gateways.IDLE_TIMEOUT:g})")  # fmt: skip
    p.add_argument(
        "--unit-map", action="append", type=unit_map, default=[], metavar="TCP=SLAVE[,...]",
        help="route a TCP unit id no --port carries to a slave address on the bus that "
        "carries it, e.g. 255=1,0=1 (0 mapped is answered, not broadcast)",
    )  # fmt: skip
    p.add_argument(
        "--broadcast-delay", type=seconds, default=BROADCAST_DELAY, metavar="SECONDS",
        help="silence after a broadcast before the bus's next request: the devices' "
        f"turnaround (default {BROADCAST_DELAY})",
    )  # fmt: skip
    add_duration_option(p)
    add_json_option(
        p,
        "JSON lines: ready, bus (a port failed, or could not be opened at the start, or "
        "is back), stopped (with the counters)",
    )
    add_serial_options(p, timeout=0.5)
    add_metrics_option(p)
    add_security_options(p, listen_address)
    g = p.add_argument_group("mbaps:// buses (Modbus/TCP Security to a TLS server)")
    g.add_argument("--port-tls-cert", metavar="FILE",
                   help="the gateway's client certificate (PEM) for mbaps:// --port")  # fmt: skip
    g.add_argument("--port-tls-key", metavar="FILE", help="its private key (PEM)")
    g.add_argument("--port-tls-ca", metavar="FILE",
                   help="the CA (PEM) that signs the mbaps:// servers' certificates")  # fmt: skip


def _same_port(port: str) -> str:
    return port if "://" in port else os.path.realpath(port)


def _routes(specs: list[BusSpec], maps: list[dict[int, int]]) -> list[dict[int, int]]:
    """Unit id -> slave address per bus; ValueError naming the flag (exit 2)."""
    seen: dict[str, str] = {}
    for s in specs:
        key = _same_port(s.port)
        if key in seen:
            raise ValueError(
                f"--port: {s.port} is given twice (as {seen[key]!r} too); give it once "
                "with all its unit ids (SERIAL=1-10,11-20)"
            )
        seen[key] = s.port
    if len(specs) > 1 and any(s.units is None for s in specs):
        raise ValueError("--port: with several buses, give each its unit ids (SERIAL=1-10)")
    units = [{u: u for u in (s.units if s.units is not None else range(1, 248))} for s in specs]
    for mapping in maps:
        for unit, slave in mapping.items():
            if any(unit in bus for bus in units):
                raise ValueError(f"--unit-map: unit id {unit} is already carried by a --port")
            bus = next((b for b in units if slave in b and b[slave] == slave), None)
            if bus is None:
                raise ValueError(f"--unit-map: slave {slave} ({unit}={slave}) is on no --port")
            bus[unit] = slave
    gateways.Routes(units)  # ValueError when a unit id is on two buses
    return units


def _bus(spec: BusSpec, args: argparse.Namespace) -> gateways.ReopeningBus:
    """The bus of ``spec``, not opened yet: the gateway opens it at its start (a port
    not there yet is down, reopened on the back-off) and reopens it the same way
    after a failure."""
    return gateways.ReopeningBus(spec.port, lambda: _connect(spec, args))


def _bus_tls(args: argparse.Namespace) -> Any:
    """The TLS context of the ``mbaps://`` buses (``--port-tls-*``), or None;
    ValueError naming the option (exit 2) before anything opens."""
    files = {"--port-tls-cert": args.port_tls_cert, "--port-tls-key": args.port_tls_key,
             "--port-tls-ca": args.port_tls_ca}  # fmt: skip
    mbaps = [s.port for s in args.port if s.port.lower().startswith("mbaps://")]
    given = [flag for flag, value in files.items() if value is not None]
    if not mbaps:
        if given:
            raise ValueError(f"{given[0]} is for an mbaps:// --port: give one")
        return None
    missing = [flag for flag in files if flag not in given]
    if missing:
        raise ValueError(f"--port {mbaps[0]} needs {', '.join(missing)}")
    from pyrtu.security.tls import client_context

    try:
        return client_context(args.port_tls_cert, args.port_tls_key, args.port_tls_ca)
    except ValueError as exc:  # its words name --tls-*: these are the --port-tls-* files
        raise ValueError(str(exc).replace("--tls-", "--port-tls-")) from None


async def _connect(spec: BusSpec, args: argparse.Namespace) -> Any:
    if spec.port.lower().startswith(("tcp://", "mbaps://")):
        from pyrtu.tcp import AsyncTcpClient

        return await AsyncTcpClient.connect(
            spec.port, timeout=args.timeout, max_in_flight=1, tls=args.bus_tls
        )
    from pyrtu.drivers.aio import AsyncMaster

    options: dict[str, Any] = serial_kwargs(args)
    options.update(timeout=args.timeout, retries=args.retries, mode=args.mode,
                   timing=args.timing, echo=args.echo, exclusive=args.exclusive,
                   broadcast_delay=args.broadcast_delay)  # fmt: skip
    if args.t35 is not None:
        options["t35"] = args.t35
    try:
        master = AsyncMaster(spec.port, **options)
    except PortBusyError as exc:  # (also when reopened: said in the bus event)
        raise exc.with_advice(BUSY_ADVICE) from exc.__cause__
    opened = getattr(master, "open", None)
    if opened is not None:
        await opened()
    return master


async def _serve(args: argparse.Namespace) -> dict[str, Any]:
    if all(a is None for a in (args.listen, args.listen_rtu, args.tls_listen, args.udp_listen)):
        raise ValueError("give one of --listen, --tls-listen, --listen-rtu or --udp-listen")
    units = _routes(args.port, args.unit_map)
    limits = gateways.GatewayLimits(
        max_connections=args.max_connections,
        max_queued_per_connection=args.max_queue,
        max_queued_per_bus=args.max_bus_queue,
        max_write_buffer=args.max_write_buffer,
        header_timeout=args.header_timeout,
        idle_timeout=args.idle_timeout,
    )
    security = open_security(args, "gateway")  # exit 2 on a bad policy, before a port opens
    args.bus_tls = _bus_tls(args)
    buses: list[Any] = []
    try:
        buses += [_bus(spec, args) for spec in args.port]
        gw = gateways.Gateway(
            list(zip(buses, units, strict=True)),
            limits,
            on_bus=lambda ev: _bus_event(args, ev),
            on_task=lambda failure: _task_failed(args, failure),
            **security.server_kwargs(),
        )
        host, port = args.listen if args.listen is not None else ("127.0.0.1", None)
        try:
            await gw.start(host, port, rtu=args.listen_rtu, tls=security.tls, udp=args.udp_listen)
        except OSError as exc:
            listeners = (
                ("--listen", args.listen, gw.address),
                ("--listen-rtu", args.listen_rtu, gw.rtu_address),
                ("--tls-listen", security.tls, gw.tls_address),
                ("--udp-listen", args.udp_listen, gw.udp_address),
            )  # (started in this order: the first given and not bound failed)
            flag = next((f for f, given, bound in listeners if given and bound is None), "--listen")
            raise OSError(exc.errno, f"{flag}: {exc.strerror}") from exc
        security.warn_if_open([gw.address, gw.rtu_address, gw.tls_address, gw.udp_address])
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        unwatch = stop_when_stdout_closes(loop, stop)  # | head -1
        started = time.monotonic()
        if args.metrics_server is not None:
            from pyrtu.metrics.gateway import GatewaySource

            args.metrics_server.serve(GatewaySource(gw, loop))
        _ready(args, gw)
        try:
            await asyncio.wait_for(stop.wait(), args.duration)
        except asyncio.TimeoutError:
            pass
        finally:
            unwatch()
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.remove_signal_handler(sig)
            await gw.close()
        return {"seconds": round(time.monotonic() - started, 3), **gw.stats()}
    finally:
        for bus in buses:
            await bus.close()
        security.close()


def _bus_event(args: argparse.Namespace, ev: gateways.BusEvent) -> None:
    """A bus's port failed or is back: one JSON line, or one line on stderr."""
    if args.json:
        emit({"type": "bus", "bus": ev.name, "up": ev.up, "error": ev.error,
              "attempts": ev.attempts, "seconds": ev.seconds,
              "starting": ev.starting})  # fmt: skip
    elif ev.up:
        print(f"pyrtu gateway: bus {ev.name} is back after {ev.seconds or 0.0:.1f} s "
              f"({ev.attempts} attempts)", file=sys.stderr, flush=True)  # fmt: skip
    else:
        what = "is not available" if ev.starting else "failed"
        error = ev.error.removeprefix(f"{ev.name}: ")
        print(f"pyrtu gateway: bus {ev.name} {what}: {error}; its requests get exception "
              "0x0A until it is back (retrying)", file=sys.stderr, flush=True)  # fmt: skip


def _task_failed(args: argparse.Namespace, failure: TaskFailure) -> None:
    """A background task of the gateway raised (it is restarted): one JSON line, or
    one line on stderr."""
    if args.json:
        emit({"type": "task_failed", "task": failure.task, "error": failure.cause,
              "retry_in": round(failure.retry_in, 3)})  # fmt: skip
    else:
        print(f"pyrtu gateway: task {failure.task} failed: {failure.cause} "
              f"(restarting in {failure.retry_in:.2f} s)", file=sys.stderr, flush=True)  # fmt: skip


def _ready(args: argparse.Namespace, gw: gateways.Gateway) -> None:
    def text(at: tuple[str, int] | None) -> str | None:
        return None if at is None else "{}:{}".format(*at)

    buses = [s.port for s in args.port]
    plain, rtu, tls, udp = (text(at) for at in (gw.address, gw.rtu_address, gw.tls_address,
                                                 gw.udp_address))  # fmt: skip
    if args.json:
        emit({"type": "ready", "listen": plain, "listen_rtu": rtu,
              "listen_tls": tls, "listen_udp": udp, "buses": buses})  # fmt: skip
    else:
        kinds = (("Modbus TCP", plain), ("RTU over TCP", rtu), ("Modbus/TCP Security", tls),
                 ("Modbus over UDP", udp))  # fmt: skip
        first, *rest = [(kind, at) for kind, at in kinds if at is not None]
        also = "".join(f" ({kind} on {at})" for kind, at in rest)
        where = first[1] if first[0] == "Modbus TCP" else f"{first[1]} ({first[0]})"
        print(
            f"pyrtu gateway: listening on {where}{also}, buses {', '.join(buses)}; Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )


def _run(args: argparse.Namespace) -> int:
    args.metrics_server = open_metrics(args.metrics, "gateway")  # before anything opens
    try:
        if args.max_connections <= SELECT_LOOP_CONNECTIONS:
            from pyrtu.drivers.aio import run as aio_run

            stats = aio_run(_serve(args))
        else:
            stats = asyncio.run(_serve(args))
    finally:
        if args.metrics_server is not None:
            args.metrics_server.close()
    if args.json:
        emit({"type": "stopped", **stats})
    else:
        print(
            f"pyrtu gateway: stopped after {stats['seconds']:.1f} s: {stats['connections']} "
            f"connections, {stats['requests']} requests, {stats['answers']} answers, "
            f"{stats['exceptions']} exceptions ({stats['timeouts']} timeouts, "
            f"{stats['busy']} busy, {stats['no_route']} no route, "
            f"{stats['bus_unavailable']} bus unavailable); {stats['bus_failures']} bus "
            f"failures, {stats['bus_recoveries']} recovered; {stats['evicted']} evicted, "
            f"{stats['header_timeouts']} header and {stats['idle_timeouts']} idle timeouts"
            + (f"; {stats['denied']} refused by the policy" if stats["denied"] else "")
            + (f"; {stats['task_failures']} task failures" if stats["task_failures"] else ""),
            file=sys.stderr,
        )
    return EXIT_OK


COMMANDS = (
    subcommand(
        "gateway",
        "Modbus TCP to RTU gateway: many TCP clients onto serial buses",
        _configure,
        _run,
        __doc__,
    ),
)
