"""The poller's ``tcp://`` buses on one `pyrtu.tcp.mux.TcpMux` (docs/many-devices.md).

A bus on the mux has no master of its own waiting in a task: each of its
transactions is one `TcpMux.submit`, and the mux reads every bus's answers (C:
csrc/rtu_mux_io.c).  While transactions are in flight, `MuxDriver` collects them
on a grid of ticks (`collect_tick`: the buses' own wake-up grid, ``lateness`` of
the shortest interval, at most 25 ms): at each, one `TcpMux.service` reads every
ready socket and ends the transactions whose timeout passed, and one
`TcpMux.take` hands the ended ones over.  For each, the driver does what the bus
task does after ``transact`` (`pyrtu.poller.driver.Poller._run_bus`: the
scheduler's ``on_response`` or ``on_failure``, the events, the write or read
waiting on it) and asks the scheduler for the bus's next request at once.  A bus
with nothing due sleeps in one heap of wake-ups shared by every bus of the mux
(on each bus's `wake_tick` grid), behind one timer of the loop.  Collecting on the grid, not at each
answer, is what makes it cheap: a thousand devices at 1 Hz wake the loop a
few dozen times a second, not a thousand (a wake-up costs tens of microseconds),
and every answer's time is still the kernel's receive time (SO_TIMESTAMPNS), not
the collection's.  A write or read someone awaits (`Poller.write`, `Poller.read`)
is not kept waiting for a tick: while one is in flight, the mux's descriptor is
watched (``add_reader``) and its answer collected as it comes.  After a tick
that collected nothing the next waits twice as long (at most 8 ticks, never past
the first timeout), so a device that never answers does not keep the loop busy.

What the buses keep: each its scheduler, its back-off, its port state and its
supervised task, which opens and connects (within the `ConnectGate`), then waits
in `MuxDriver.drive` until the connection fails (a `PortError`: the task reports
it and reconnects, as on every other bus) or the poller stops.  A fault of the
poller itself in a bus's step ends its `drive` with that error, so the bus task's
supervision reports it and starts it again.  The transaction's errors are the
asyncio master's (`pyrtu.tcp.protocol.TcpClientProtocol` judges the ended
transactions), its ``timeout`` and ``retries`` the bus's.

So a thousand devices cost the event loop a callback per batch of answers and a
few calls per transaction, not a task switch, two timers and a transport callback
each (bench/bench_many_devices.py measures both).
"""

from __future__ import annotations

import asyncio
import functools
import heapq
import itertools
import logging
import math
import socket
import time
from collections.abc import Iterable, Sequence
from typing import Any, Protocol

from pyrtu.drivers._portname import url_scheme
from pyrtu.drivers.xfer import TCP_ANSWER, TcpScan, TcpXferReport
from pyrtu.pdu import requests as request_table
from pyrtu.pdu.errors import NoResponseError
from pyrtu.pdu.requests import Call, answer_pdu
from pyrtu.tcp.client import connect_error, parse_tcp_url, where_of
from pyrtu.tcp.link import TcpLink
from pyrtu.tcp.mux import REPEATING, RESENT, MuxDone, TcpMux
from pyrtu.tcp.mux_backends import available, open_mux
from pyrtu.tcp.protocol import TcpClientProtocol
from pyrtu.tcp.sockets import set_nodelay

from ._schedule_parts import POLL
from .busrun import BusRun
from .config import Bus
from .events import Event, Unchanged
from .masters import BY_FUNCTION, is_port_error
from .schedule import ScheduledRequest


class PollerSide(Protocol):
    """What `MuxDriver` does through its `pyrtu.poller.driver.Poller`: the steps
    the bus task takes around a transaction, shared rather than copied."""

    _running: bool

    def _silent(self, run: BusRun, req: ScheduledRequest) -> None: ...

    @staticmethod
    def _args(req: ScheduledRequest) -> tuple[Any, ...]: ...

    def _port_ok(self, run: BusRun, now: float) -> None: ...

    def _dispatch(self, events: Sequence[Event | Unchanged], run: BusRun | None = None) -> None: ...


_debug = functools.partial(logging.getLogger("pyrtu.drivers.master").isEnabledFor, logging.DEBUG)

#: the master keywords a bus on the mux honours (any other keeps it on its own master)
MUX_KEYS = frozenset(("timeout", "retries"))


#: the longest gap between collections while transactions are in flight, in ticks
MAX_GAP = 8


def collect_tick(ticks: Iterable[float]) -> float:
    """The grid the mux is collected on: the finest of its buses' wake-up grids
    (`pyrtu.poller.driver.wake_tick`; 10 ms when none has one)."""
    return min((t for t in ticks if t > 0), default=0.01)


def on_mux(bus: Bus) -> bool:
    """Whether ``bus`` runs on the mux: a plain ``tcp://`` bus (no TLS) whose master
    keywords are only ``timeout`` and ``retries``, where there is a mux (not on a
    platform whose only selector is select(): `pyrtu.tcp.mux_backends.available`)."""
    port = bus.port
    return (
        isinstance(port, str)
        and url_scheme(port) == "tcp"
        and bus.tls is None
        and set(bus.master_options) <= MUX_KEYS
        and available()
    )


class _Ended:
    """A `pyrtu.drivers.xfer.TcpXferRunner`'s report of a transaction the mux ended
    (what `TcpClientProtocol.settle` judges)."""

    __slots__ = ("_done",)

    def __init__(self, done: MuxDone) -> None:
        self._done = done

    def end(self) -> float:
        return self._done.end

    def report(self) -> TcpXferReport:
        d = self._done
        # the answer as the runner's buffer holds it: an ADU (its header's bytes
        # are the transaction id and the length; the late ones were dropped)
        n = len(d.adu)
        data = d.tid.to_bytes(2, "big") + b"\0\0" + n.to_bytes(2, "big") + d.adu
        scan = TcpScan(len(data) if n else 0, 0, len(data) if n else 0, d.late, 0, d.err)
        return TcpXferReport(d.status, d.start, d.end, data, scan, d.err, d.stage)


class MuxBus:
    """A bus's connection on the mux: the "master" `Poller` opens, connects and
    closes for it (its transactions go through `MuxDriver`)."""

    def __init__(self, driver: MuxDriver, bus: Bus) -> None:
        options = bus.master_options
        self.driver = driver
        self.host, self.port = parse_tcp_url(str(bus.port))
        self.where = where_of(self.host, self.port)
        self.proto = TcpClientProtocol(timeout=float(options.get("timeout", 1.0)),
                                       where=self.where)  # fmt: skip
        self.retries = int(options.get("retries", 0))
        self.conn: int | None = None

    @property
    def counters(self) -> dict[str, int]:
        return dict(self.proto.counters)

    @property
    def last_answer_time(self) -> float | None:
        return self.proto.answer_end

    async def connect(self) -> None:
        """Connect (within the bus's timeout) and attach to the mux; `PortError`
        (``cannot connect: ...``) when it cannot be made."""
        if self.conn is not None:
            return
        loop = asyncio.get_running_loop()
        timeout = self.proto.timeout
        sock: socket.socket | None = None
        try:
            infos = await loop.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)
            family, kind, proto, _, address = infos[0]
            sock = socket.socket(family, kind, proto)
            sock.setblocking(False)
            await asyncio.wait_for(loop.sock_connect(sock, address), timeout)
        except (OSError, asyncio.TimeoutError) as exc:
            if sock is not None:
                sock.close()
            raise connect_error(self.where, exc, timeout) from exc
        except BaseException:
            if sock is not None:
                sock.close()
            raise
        set_nodelay(sock)
        self.conn = self.driver.mux.attach(sock)

    async def transact(self, req: Any, slave: int, *args: Any) -> tuple[Any, float]:
        """(A bus on the mux is driven by `MuxDriver`, not through this.)"""
        raise RuntimeError("a bus on the mux has its transactions driven by MuxDriver")

    async def close(self) -> None:
        conn, self.conn = self.conn, None
        if conn is not None:
            self.driver.mux.detach(conn)


class _Fault(Exception):
    """A bus's step raised (a fault of the poller, not of the port)."""

    def __init__(self, error: BaseException) -> None:
        super().__init__(str(error))
        self.error = error


class _Drive:
    """What `MuxDriver` keeps of one bus while it drives it."""

    __slots__ = (
        "call",
        "exit",
        "left",
        "link",
        "polls",
        "repeat",
        "run",
        "timer",
        "token",
        "urgent",
        "wake_seq",
    )

    def __init__(self, run: BusRun, link: MuxBus, exit: asyncio.Future[BaseException]) -> None:
        self.run = run
        self.link = link
        self.exit = exit
        self.token = 0  # the transaction in flight (0: none)
        self.call: Call | None = None
        self.left = 0  # its retries left
        self.timer: asyncio.TimerHandle | None = None  # its offline_due
        self.wake_seq = 0  # its entry in the wake-up heap (0: none)
        self.urgent = False  # someone awaits its transaction in flight
        #: the mux repeats its poll (`TcpMux.repeat`): ``token`` stays its own and
        #: ``run.inflight`` the request repeated, between transactions too
        self.repeat = False
        #: by poll block (its id): the block, its Call, its last answer and value
        #: (the same bytes again: the same value, not decoded again)
        self.polls: dict[int, list[Any]] = {}


class MuxDriver:
    """Drives the poller's buses on one mux (see the module docstring)."""

    def __init__(self, poller: PollerSide, capacity: int, tick: float) -> None:
        self.poller = poller
        self.capacity = capacity
        self.mux: TcpMux = open_mux(capacity)
        self._loop = asyncio.get_running_loop()
        self._tick = tick
        self._collect: asyncio.TimerHandle | None = None
        self._collect_at = float("inf")
        self._gap = 1  # ticks until the next collection
        self._urgent = 0  # awaited transactions in flight (the descriptor watched)
        self._drives: dict[int, _Drive] = {}  # by token
        self._by_run: dict[str, _Drive] = {}
        self._tokens = itertools.count(1)
        self._wakes: list[tuple[float, int, _Drive]] = []
        self._wake_seqs = itertools.count(1)
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = float("inf")
        self.closed = False

    def open(self, bus: Bus) -> MuxBus:
        """The bus's connection (not connected yet): `Poller`'s master factory."""
        return MuxBus(self, bus)

    async def drive(self, run: BusRun) -> BaseException:
        """Drive ``run``'s transactions on the mux until its connection fails:
        returns that error (the bus task reports it and reconnects).  A fault of
        the poller in one of its steps is raised (`_Fault`'s error)."""
        link = run.master
        assert isinstance(link, MuxBus)
        d = _Drive(run, link, self._loop.create_future())
        self._by_run[run.bus.name] = d
        try:
            self._step(d, time.monotonic())
            error = await d.exit
        finally:
            self._release(d)
        if isinstance(error, _Fault):
            raise error.error
        return error

    def kick(self, run: BusRun) -> None:
        """A write or read was submitted to ``run``: step it now if it is idle."""
        d = self._by_run.get(run.bus.name)
        if d is None or d.exit.done():
            return
        if d.repeat:
            self._stop_repeat(d)  # (a record still to come: its outcome steps the bus)
        if d.token == 0:
            d.wake_seq = 0  # (its heap entry goes stale)
            self._loop.call_soon(self._guarded_step, d)

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for timer in (self._timer, self._collect):
            if timer is not None:
                timer.cancel()
        if self._urgent:
            self._loop.remove_reader(self.mux.fd)
        self.mux.close()

    # ------------------------------------------------------------------ the steps

    def _release(self, d: _Drive) -> None:
        """``d`` is no longer driven: its transaction in flight is abandoned (not
        failed: nothing counts, a poll block stays due), as the bus task does when
        it is cancelled."""
        if self._by_run.get(d.run.bus.name) is d:
            del self._by_run[d.run.bus.name]
        d.wake_seq = 0
        if d.timer is not None:
            d.timer.cancel()
            d.timer = None
        run = d.run
        if d.repeat:
            self._stop_repeat(d)
            exit = d.exit
            if d.token == 0 and not (
                exit.done() and not exit.cancelled() and isinstance(exit.result(), _Fault)
            ):  # (a fault in its outcome leaves the request to the bus task's supervision)
                run.inflight = None
        if d.token:
            self._drives.pop(d.token, None)
            d.token = 0
            self._settled(d)
            req, fut = run.inflight, run.inflight_future
            run.inflight = run.inflight_future = None
            if req is not None:
                run.sched.on_port_failure(req)
            if fut is not None and not fut.done():
                fut.cancel()

    def _end(self, d: _Drive, error: BaseException) -> None:
        if not d.exit.done():
            d.exit.set_result(error)

    def _guarded_step(self, d: _Drive) -> None:
        if d.exit.done() or d.token:
            return
        try:
            self._step(d, time.monotonic())
        except Exception as exc:  # a fault of the poller: the bus task's supervision
            self._end(d, _Fault(exc))

    def _step(self, d: _Drive, now: float) -> None:
        """Send ``d``'s next request, or sleep until the scheduler's deadline."""
        run, poller = d.run, self.poller
        if not poller._running:
            return
        sched = run.sched
        req = sched.next_request(now)
        if req is None:
            deadline = sched.deadline()
            if deadline is not None:
                self._sleep(d, run.wake_at(deadline))
            return
        fut = run.pending.pop(req.tag, None) if req.tag else None
        run.inflight, run.inflight_future = req, fut
        due = sched.offline_due(req)
        if due is not None:
            d.timer = self._loop.call_later(max(0.0, due - now), poller._silent, run, req)
        block = req.block if req.kind == POLL else None
        poll = None if block is None else d.polls.get(id(block))
        if poll is not None and poll[0] is block:
            d.call = poll[1]
        else:
            try:
                request = BY_FUNCTION[req.function]
                d.call = request_table.call_of(request, req.slave, poller._args(req)[1:], {},
                                               TcpLink.address)  # fmt: skip
            except Exception as exc:  # (an argument the request refuses): its outcome
                self._outcome(d, req, exc, None, now)
                return
            if block is not None:
                if len(d.polls) > 4 * len(sched.blocks) + 16:
                    d.polls.clear()  # (blocks planned again: the old ones go)
                d.polls[id(block)] = [block, d.call, None, None]
        d.left = d.link.retries
        if self._send(d) and sched.steady(req):  # the mux sends it on (`_stop_repeat`)
            assert d.link.conn is not None and req.task is not None
            self.mux.repeat(d.link.conn, req.task.due, req.task.block.interval)
            d.repeat = True

    def _stop_repeat(self, d: _Drive) -> None:
        """End ``d``'s repeat.  If its last transaction is over (its record taken),
        ``d`` has no token any more; else that transaction's record still comes,
        without `REPEATING`, and its outcome steps the bus."""
        d.repeat = False
        link = d.link
        try:
            pending = link.conn is not None and self.mux.unrepeat(link.conn)
        except ValueError:  # (detached already: nothing comes)
            pending = False
        if not pending:
            self._drives.pop(d.token, None)
            d.token = 0
            self._settled(d)

    def _send(self, d: _Drive) -> bool:
        """Submit ``d``'s call; whether it is in flight (False: it ended at once)."""
        call, link = d.call, d.link
        assert call is not None and link.conn is not None
        unit, pdu, decode = call
        tid, body, awaited = link.proto.begin(unit, pdu, decode is not None)
        d.token = next(self._tokens)
        self._drives[d.token] = d
        if d.run.inflight_future is not None and not d.urgent:
            d.urgent = True  # someone awaits it: collected as it comes
            self._urgent += 1
            if self._urgent == 1:
                self._loop.add_reader(self.mux.fd, self._ready)
        if self.mux.submit(link.conn, d.token, tid, unit, body, link.proto.timeout, awaited):
            self._loop.call_soon(self._ready)  # (ended at once: no descriptor says so)
            return False
        self._gap = 1
        self._collect_by(self._grid_after(time.monotonic()))
        return True

    def _settled(self, d: _Drive) -> None:
        """``d``'s transaction is no longer in flight."""
        if d.urgent:
            d.urgent = False
            self._urgent -= 1
            if not self._urgent:
                self._loop.remove_reader(self.mux.fd)

    def _grid_after(self, now: float) -> float:
        """The `_gap`-th grid point after ``now``."""
        return (math.floor(now / self._tick + 1e-6) + self._gap) * self._tick

    def _collect_by(self, at: float) -> None:
        """Have the mux collected at ``at``, unless a collection is due sooner."""
        if at >= self._collect_at:
            return
        if self._collect is not None:
            self._collect.cancel()
        self._collect_at = at
        self._collect = self._loop.call_at(at, self._collected)

    def _collected(self) -> None:
        """A collection's tick: the answers and timeouts; the next tick while
        transactions are in flight (further apart after one that found none,
        never past the first timeout's grid point)."""
        self._collect, self._collect_at = None, float("inf")
        found = self._ready()
        deadline = self.mux.deadline()
        if deadline is None:
            return
        self._gap = 1 if found else min(self._gap * 2, MAX_GAP)
        now = time.monotonic()
        due = max(math.ceil(deadline / self._tick - 1e-6) * self._tick, now)
        self._collect_by(min(self._grid_after(now), due))

    def _sleep(self, d: _Drive, at: float) -> None:
        d.wake_seq = seq = next(self._wake_seqs)
        heapq.heappush(self._wakes, (at, seq, d))
        if at < self._timer_at:
            if self._timer is not None:
                self._timer.cancel()
            self._timer_at = at
            self._timer = self._loop.call_at(at, self._wake)

    def _wake(self) -> None:
        """The earliest sleeping bus is due: step every bus due by now."""
        self._timer, self._timer_at = None, float("inf")
        now = time.monotonic()
        wakes = self._wakes
        while wakes and wakes[0][0] <= now:
            _, seq, d = heapq.heappop(wakes)
            if seq == d.wake_seq:
                d.wake_seq = 0
                self._guarded_step(d)
        while wakes and wakes[0][1] != wakes[0][2].wake_seq:
            heapq.heappop(wakes)  # (stale: kicked, or no longer driven)
        if wakes:
            self._timer_at = wakes[0][0]
            self._timer = self._loop.call_at(self._timer_at, self._wake)

    def _ready(self) -> int:
        """Collect: the ended transactions' outcomes, then each one's bus's next
        step; how many ended.  (The mux's own failure ends every bus's drive with
        it.)"""
        mux = self.mux
        try:
            records = mux.take() if mux.service() else []
        except OSError as exc:
            for driven in list(self._by_run.values()):
                self._end(driven, exc)
            return 0
        drives = self._drives
        for rec in records:
            d = drives.get(rec.token)
            if d is None or d.token != rec.token:
                continue  # (its bus stopped being driven meanwhile)
            if not rec.flags & REPEATING:  # (else the repeat goes on: the token stays)
                del drives[rec.token]
                d.token = 0
                d.repeat = False
                self._settled(d)
            try:
                if rec.flags & RESENT:  # sent by the repeat: as if by `_step`
                    d.link.proto.repeated(rec.tid)
                    assert d.run.inflight is not None
                    d.run.sched.repeated(d.run.inflight, rec.start)
                self._ended(d, rec)
            except Exception as exc:  # a fault of the poller: the bus task's supervision
                self._end(d, _Fault(exc))
        return len(records)

    def _ended(self, d: _Drive, rec: MuxDone) -> None:
        run, link, call = d.run, d.link, d.call
        req = run.inflight
        assert call is not None and req is not None
        proto = link.proto
        value: Any = None
        error: BaseException | None = None
        end = rec.end
        if rec.status == TCP_ANSWER and not rec.late and not rec.err:
            if rec.adu:  # (else a broadcast went out)
                proto.counters["responses"] += 1
                proto.answer_end = end
                if _debug():  # (`pyrtu -vv`: every frame, as the asyncio client logs it)
                    ms = (end - rec.start) * 1e3
                    TcpClientProtocol._log_answer(rec.tid, rec.adu[0], rec.adu[1:], ms)
                    if d.repeat:  # (its requests are logged only when sent by `_send`)
                        self._stop_repeat(d)
        else:
            try:
                raw = call.decode is answer_pdu
                settled = proto.settle(rec.tid, call.slave, call.pdu[0], raw, _Ended(rec))  # type: ignore[arg-type]
            except Exception as exc:
                error = exc
            else:
                if settled is None:
                    rec = rec._replace(adu=b"")
                else:
                    rec = rec._replace(adu=bytes((call.slave,)) + settled)
                if proto.answer_end is not None:
                    end = proto.answer_end
        if error is None and call.decode is not None and rec.adu:
            poll = d.polls.get(id(req.block)) if req.kind == POLL else None
            if poll is not None and poll[0] is req.block and poll[2] == rec.adu:
                value = poll[3]  # the same bytes as last time: the same registers
            else:
                try:
                    value = call.decode(rec.adu[1:])
                except Exception as exc:  # a malformed answer: the decoder's error
                    error = exc
                    if d.repeat:
                        self._stop_repeat(d)
                else:
                    if poll is not None and poll[0] is req.block:
                        poll[2], poll[3] = rec.adu, value
        elif error is None and call.decode is None:
            end = time.monotonic()
        if isinstance(error, NoResponseError) and d.left > 0:
            d.left -= 1
            self._send(d)  # (a retry: a new transaction id)
            return
        if error is not None and is_port_error(error):
            self._port_failed(d, req, error)
            return
        self._outcome(d, req, error, value, end)

    def _port_failed(self, d: _Drive, req: ScheduledRequest, error: BaseException) -> None:
        run = d.run
        fut = run.inflight_future
        run.inflight = run.inflight_future = None
        if d.timer is not None:
            d.timer.cancel()
            d.timer = None
        if fut is not None and not fut.done():
            fut.set_exception(error)
        run.sched.on_port_failure(req)
        self._end(d, error)

    def _outcome(
        self, d: _Drive, req: ScheduledRequest, error: BaseException | None, value: Any, end: float
    ) -> None:
        """``req`` answered (``value``) or failed (``error``), as the bus task's
        transaction ends (`Poller._run_bus`); then the bus's next step."""
        run, poller = d.run, self.poller
        fut = run.inflight_future
        if d.timer is not None:
            d.timer.cancel()
            d.timer = None
        sched = run.sched
        if error is not None:
            if fut is not None and not fut.done():
                fut.set_exception(error)
            now = time.monotonic()
            poller._port_ok(run, now)
            events: Any = sched.on_failure(req, error, now)
        else:
            if not run.worked or run.reconnect.down:  # (else nothing for it to do)
                poller._port_ok(run, time.monotonic())
            events = sched.on_response(req, value, end)
            if fut is not None and not fut.done():
                fut.set_result(value)
        if d.repeat:  # the mux sends the next: the request stays in flight
            if events:
                poller._dispatch(events, run)
            return
        run.inflight = run.inflight_future = None
        if events:
            poller._dispatch(events, run)
        self._step(d, time.monotonic())


__all__ = ["MUX_KEYS", "MuxBus", "MuxDriver", "on_mux"]
