"""``pyrtu simulate ... --tcp HOST:PORT``: a simulated drive over Modbus TCP.

The drive's slave (the one on ``--port``, or one without a port when only ``--tcp``
is given: the drive's functions, handlers and identification over its DataStore)
served by `pyrtu.tcp.server.TcpServer` from an event loop in a thread of its own.

``--tcp HOST:FIRST-LAST``: a device per port of the range, each with its own
simulator and DataStore, one `TcpServer` (one listening socket) per port, all on
that one event loop (`TcpThread.many`); `ServerGroup` adds up their counters and
names the port of each health problem.  `tcp_range` parses the flag and
`open_files_for` makes sure the process may open a socket per port and client.

Supervised: the server's tasks are the gateway's (restarted on the back-off, each
failure handed to ``on_task``); the thread itself ending while it should serve (its
loop stopped, or left by a ``SystemExit`` out of a callback) is `failure`, which the
command checks between its waits and ends on (exit 1, one line).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

from pyrtu.core.line import LINE_DEFAULTS, LineConfig
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.drivers.supervise import TaskFailure, cause
from pyrtu.security.tls import TlsListen
from pyrtu.tcp.server import TcpServer

log = logging.getLogger("pyrtu.cli")

#: the most ports one ``--tcp HOST:FIRST-LAST`` serves
MAX_RANGE = 10000
#: open files a process needs besides its sockets (the interpreter, pipes, the pty)
_SPARE_FILES = 64


def tcp_range(text: str) -> tuple[str, int, int]:
    """``--tcp``: HOST:PORT (0: any free port) or HOST:FIRST-LAST (a device per port,
    1..65535, at most `MAX_RANGE` ports); ``[::1]:502`` for IPv6.  (host, first,
    last); argparse's error names the flag."""
    host, sep, ports = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    first_text, dash, last_text = ports.partition("-")
    if not dash:
        last_text = first_text
    numbers = first_text.isdigit() and last_text.isdigit()
    if not sep or not host or not numbers:
        raise argparse.ArgumentTypeError(
            f"expected HOST:PORT or HOST:FIRST-LAST (a range of ports), not {text!r}"
        )
    first, last = int(first_text), int(last_text)
    if not dash:
        if first > 65535:
            raise argparse.ArgumentTypeError(f"a port is 0..65535, not {first} (in {text!r})")
        return host, first, first
    for port in (first, last):
        if not 1 <= port <= 65535:
            raise argparse.ArgumentTypeError(
                f"a port of a range is 1..65535, not {port} (in {text!r}; "
                "port 0, any free port, is for a single port)"
            )
    if last < first:
        raise argparse.ArgumentTypeError(f"the range {first}-{last} ends before it starts")
    if last - first + 1 > MAX_RANGE:
        raise argparse.ArgumentTypeError(
            f"the range {first}-{last} has {last - first + 1} ports; at most {MAX_RANGE}"
        )
    return host, first, last


def open_files_for(ports: int) -> None:
    """Let the process open a listening socket and a client's per port: the soft
    limit of open files raised to what that needs (up to the hard limit).
    ValueError naming ``--tcp`` when the hard limit is too low."""
    import resource  # (POSIX only: pyrtu's CLI imports on Windows too)

    need = 2 * ports + _SPARE_FILES
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= need:
        return
    if hard != resource.RLIM_INFINITY and hard < need:
        raise ValueError(
            f"--tcp: {ports} ports need {need} open files (a socket per port and per "
            f"client), but this process may open at most {hard} (ulimit -Hn): "
            "serve a shorter range, or raise the limit"
        )
    resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))


#: `pyrtu.Slave` keywords that belong to the serial line (not to a TCP-only slave)
_LINE_KEYS = frozenset(LINE_DEFAULTS)


def tcp_only_slave(sim: Any, address: int) -> SlaveBase:
    """The drive's slave without a port (functions, handlers, identification)."""
    options = dict(sim.slave_options())
    for key in _LINE_KEYS & set(options):
        del options[key]  # frames are MBAP on TCP: no RTU lengths, no ASCII
    options.pop("response_delay", None)  # a turnaround of the serial line
    app = SlaveBase(address, sim.store, line=LineConfig(), **options)
    for fc, (handler, _req, _resp, broadcast) in sim.handlers().items():
        app.register_function(fc, handler, broadcast=broadcast)
    app.on_request(sim.telegram)
    with sim.lock:
        sim._served_at(address)
    return app


def _summed(parts: Sequence[dict[str, object]]) -> dict[str, object]:
    """`TcpServer.stats` of several servers as one: numbers added, lists joined."""
    total: dict[str, object] = {}
    for part in parts:
        for key, value in part.items():
            have = total.get(key)
            if isinstance(value, list):
                total[key] = (have if isinstance(have, list) else []) + value
            elif isinstance(value, int | float) and not isinstance(value, bool):
                total[key] = (have if isinstance(have, int | float) else 0) + value
            else:
                total[key] = value
    return total


class ServerGroup:
    """The `TcpServer` of each port of a range, counted as one server: its
    ``counters`` and `stats` added up, its `health` naming the port of each
    problem (what ``--metrics`` and the command's counters read)."""

    def __init__(self, servers: Sequence[TcpServer]) -> None:
        self.servers = list(servers)

    @property
    def address(self) -> tuple[str, int] | None:
        """The first port's (host, port)."""
        return self.servers[0].address if self.servers else None

    @property
    def tls_address(self) -> tuple[str, int] | None:
        """The first port's TLS listener's (none on a range: `--tls-listen` takes
        one port)."""
        return self.servers[0].tls_address if self.servers else None

    @property
    def udp_address(self) -> tuple[str, int] | None:
        """The first port's UDP listener's (none on a range: ``--udp`` takes one port)."""
        return self.servers[0].udp_address if self.servers else None

    @property
    def counters(self) -> dict[str, int]:
        total: dict[str, int] = {}
        for server in self.servers:
            for key, value in server.counters.items():
                total[key] = total.get(key, 0) + value
        return total

    def stats(self) -> dict[str, object]:
        return _summed([server.stats() for server in self.servers])

    def health(self) -> list[str]:
        problems = []
        for server in self.servers:
            where = "port ?" if server.address is None else f"port {server.address[1]}"
            problems += [f"{where}: {text}" for text in server.health()]
        return problems


class TcpThread:
    """A `TcpServer` for ``app`` on its own event loop thread (`many`: one per port
    of a range, `ServerGroup` as ``server``)."""

    def __init__(
        self,
        app: Any,
        host: str,
        port: int | None,
        on_task: Callable[[TaskFailure], None] | None = None,
        tls: TlsListen | None = None,
        udp: tuple[str, int] | None = None,
        **security: Any,
    ) -> None:
        # security: TcpServer's policy, audit and on_denied (pyrtu.cli._security);
        # port None: no Modbus TCP listener (--udp alone)
        self.server: TcpServer | ServerGroup = TcpServer(app, on_task=on_task, **security)
        self._begin([(self.server, port)], host, tls, udp)

    @classmethod
    def many(
        cls,
        apps: Sequence[Any],
        host: str,
        ports: Sequence[int],
        on_task: Callable[[TaskFailure], None] | None = None,
        **security: Any,
    ) -> TcpThread:
        """A `TcpServer` for each of ``apps`` on the port of the same rank, all on one
        event loop.  A port that cannot be bound is an OSError naming it (the
        servers started before it closed again)."""
        self = cls.__new__(cls)
        servers = [TcpServer(app, on_task=on_task, **security) for app in apps]
        self.server = ServerGroup(servers)
        self._begin(list(zip(servers, ports, strict=True)), host, None, None)
        return self

    def _begin(
        self,
        listen: Sequence[tuple[Any, int | None]],
        host: str,
        tls: TlsListen | None,
        udp: tuple[str, int] | None,
    ) -> None:
        self.loop = asyncio.new_event_loop()
        self.loop.set_exception_handler(self._unhandled)
        self._listen = [server for server, _ in listen]
        self._stopping = False
        self._failure: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="pyrtu-simulate-tcp", daemon=True)
        self._thread.start()
        try:
            starting = _start_all(listen, host, tls, udp)
            asyncio.run_coroutine_threadsafe(starting, self.loop).result(60)
        except BaseException:
            self.stop()
            raise

    def _unhandled(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """What the loop could give to no one (a connection's callback that raised;
        after the thread died, the tasks it left): one line on stderr while it
        serves, the log (``-v``) with the trace."""
        error = context.get("exception")
        text = str(context.get("message", "unhandled error"))
        if error is not None:
            text = f"{text}: {cause(error)}"
        log.debug("TCP server: %s", text, exc_info=error)
        if self._failure is None and not self._stopping:
            print(f"pyrtu simulate: TCP server: {text}", file=sys.stderr, flush=True)

    def _main(self) -> None:
        try:
            self.loop.run_forever()
        except BaseException as exc:  # SystemExit, KeyboardInterrupt out of a callback
            self._failure = exc
        else:
            if not self._stopping:
                self._failure = RuntimeError("its event loop stopped")

    @property
    def failure(self) -> BaseException | None:
        """Why the server's thread ended while it should serve (None: it serves)."""
        return None if self._thread.is_alive() else self._failure

    @property
    def address(self) -> tuple[str, int] | None:
        """The (host, port) of the (first) Modbus TCP listener; None with --udp alone."""
        return self.server.address

    def stop(self) -> None:
        self._stopping = True
        if self.loop.is_closed():
            return
        if not self._thread.is_alive():  # it died: nothing runs the loop any more
            self.loop.close()
            return
        # (a server never started closes as nothing: each closes what it listens on)
        asyncio.run_coroutine_threadsafe(_close_all(self._listen), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(30)
        self.loop.close()


async def _start_all(
    listen: Sequence[tuple[TcpServer, int | None]],
    host: str,
    tls: TlsListen | None,
    udp: tuple[str, int] | None,
) -> None:
    """Start each server on its port, in order (the first with the TLS listener of
    ``tls`` and the UDP listener of ``udp``, if any); a port that cannot be bound is
    an OSError naming its flag and the port (and why)."""
    for rank, (server, port) in enumerate(listen):
        also = (tls, udp) if rank == 0 else (None, None)
        try:
            await server.start(host, port, tls=also[0], udp=also[1])
        except OSError as exc:
            reason = exc.strerror or str(exc)
            flag, (at_host, at_port) = _unbound(server, host, port, *also)
            raise OSError(
                exc.errno, f"{flag}: cannot listen on {at_host}:{at_port}: {reason}"
            ) from exc


def _unbound(
    server: TcpServer,
    host: str,
    port: int | None,
    tls: TlsListen | None,
    udp: tuple[str, int] | None,
) -> tuple[str, tuple[str, int | None]]:
    """The flag and address of the listener ``server.start`` could not bind: the first
    given and not bound (they are bound in this order)."""
    for flag, at, bound in (
        ("--tcp", None if port is None else (host, port), server.address),
        ("--tls-listen", None if tls is None else (tls.host, tls.port), server.tls_address),
        ("--udp", udp, server.udp_address),
    ):
        if at is not None and bound is None:
            return flag, at
    return "--tcp", (host, port)


async def _close_all(servers: Sequence[TcpServer]) -> None:
    await asyncio.gather(*(server.close() for server in servers))
