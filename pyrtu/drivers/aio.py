"""asyncio drivers: `AsyncMaster` (and `AsyncSlave`) on the sans-I/O protocols.

::

    async def main() -> None:
        async with AsyncMaster("/dev/ttyUSB0", 19200, timeout=0.5) as bus:
            speed, current = await bus.read_holding_registers(1, 2, 2)

    asyncio.run(main())

`AsyncMaster` takes the keywords of `pyrtu.Master` and has its methods, as
coroutines.  One event loop serves many ports: each `AsyncMaster` runs one
transaction at a time through a first-come-first-served queue (an
`asyncio.Lock`, which wakes its waiters in order), and different ports run in
parallel.  Waiting is a timer or ``loop.add_reader`` on the port's file
descriptor, run from the loop's callbacks (the awaiting task wakes once per
transaction); while an answer comes in, the driver sleeps the character times
of the bytes it still needs instead of waking per byte.  A repeated request on a
descriptor goes as one `Xfer` on the port's xfer thread (the backend's
`AsyncXferRunner`: a C thread without the GIL, which keeps t3.5 and the reads'
times with ``clock_nanosleep``), and the loop wakes once, when it is over.  Ports
without a descriptor (pyserial URLs such as ``loop://``, Windows COM ports) are read
with pyserial's blocking reads in a worker thread of their own.

Cancelling an ``await`` leaves the bus consistent: the protocol notes that a
late answer may come, and the next transaction waits it out before sending;
``close()`` waits it out too before the port is closed (the next master to open
the port would transmit over it).

A port that fails is closed and reopened at a later request on the back-off, as
`pyrtu.Master`'s (`pyrtu.drivers.master.SerialLink.ready`); an ``rtu+tcp://``
connection is made again the same way, its connect on a worker thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future as ThreadFuture
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

from pyrtu import pdu as pdus
from pyrtu.core.rules import LengthRule
from pyrtu.drivers import _ptimer, xfer, xfer_runners
from pyrtu.drivers._slack import tighten_this_thread
from pyrtu.drivers.links import Link
from pyrtu.drivers.master import Master, MasterBase, SerialLink
from pyrtu.drivers.sync_io import plan_of, read_now, report
from pyrtu.pdu import requests as request_table
from pyrtu.pdu.errors import PortError
from pyrtu.pdu.requests import Call, Request, Rules
from pyrtu.protocol.client import ClientProtocol, Send, Wait
from pyrtu.protocol.client_actions import Done, Xfer

if TYPE_CHECKING:
    from pyrtu.tcp.link import AsyncTcpLink

_monotonic = time.monotonic


class AsyncMaster(MasterBase):
    """A Modbus master on one serial line for asyncio (see the module docstring)."""

    _PIPELINES = True  # tcp:// ports keep up to max_in_flight requests on the wire

    def _open(self, link: Any) -> Link:
        self._lock = asyncio.Lock()
        self._reader: ThreadPoolExecutor | None = None
        self._inflight: ThreadFuture[bytes] | None = None  # a thread read a cancel left
        if not isinstance(link, SerialLink):  # a link that runs its transactions itself
            self._tcp: AsyncTcpLink | None = link
            opened: Link = link
            return opened
        self._tcp = None
        self._serial_link = link
        self._proto = link.proto
        self._fd = link.port.fd
        #: the port ``_fd`` is of (the link reopens a port that failed: a new one)
        self._known_port = link.port
        #: the link's reopen on a worker thread (`_ready`)
        self._reopening: asyncio.Future[None] | None = None
        # a repeated request's Xfer on a thread of the backend's (see _submit)
        self._ax: xfer.AsyncXferRunner | None = None
        self._ax_call: Callable[[xfer.XferResult], None] | None = None
        self._ax_over: asyncio.Future[None] | None = None  # the xfer under way
        self._ax_loop: asyncio.AbstractEventLoop | None = None  # the loop watching it
        if self._fd is None:
            self._reader = ThreadPoolExecutor(1, thread_name_prefix=f"pyrtu-read-{link.port.name}")
        return link

    # ------------------------------------------------------------- the driver

    async def _readable(self, deadline: float) -> bool:
        """Wait until the port has input or ``deadline`` passes (fd ports)."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[bool] = loop.create_future()
        fd = self._fd
        assert fd is not None

        def ready(value: bool) -> None:
            if not fut.done():
                fut.set_result(value)

        loop.add_reader(fd, ready, True)
        timer = _ptimer.call_at(loop, deadline, ready, False)
        try:
            return await fut
        finally:
            timer.cancel()
            loop.remove_reader(fd)

    async def _read_thread(self, deadline: float) -> bytes:
        """Bytes within ``deadline`` through pyserial's blocking read in the port's thread."""
        loop = asyncio.get_running_loop()
        assert self._reader is not None
        if self._inflight is None:
            wait = max(0.0, deadline - _monotonic())
            self._inflight = self._reader.submit(self.port.read, wait)
        fut = self._inflight
        data = await asyncio.wrap_future(fut, loop=loop)
        self._inflight = None
        return data

    async def _wait(self, action: Wait) -> bytes:
        """A `Wait` as this task's awaits: a timer, the descriptor (``listen``) or a
        thread read (no descriptor); then the bytes read (b"": none)."""
        until = action.until
        if action.listen and self._fd is None:
            return await self._read_thread(until)
        if until > _monotonic():
            if action.listen:
                await self._readable(until)
            else:
                await _ptimer.sleep_until(until)
        if self._inflight is not None:  # a thread read a cancel left behind
            return await self._read_thread(until)
        return self.port.read(0)

    async def _transmit(self, adu: bytes) -> tuple[float, float]:
        port = self.port
        if not port.has_wire:
            return port.write(adu)  # no wire: the write returns at once
        # a real line: Port.write waits for the drain (tcdrain), off the loop's thread
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(None, port.write, adu)

    # ------------------------------------------------------- the xfer thread

    def _submit(self, action: Xfer, then: Callable[[xfer.XferResult], None]) -> None:
        """Start an `Xfer` on the port's xfer thread (the backend's
        `AsyncXferRunner`: C, without the GIL); ``then(report)`` runs in the loop when
        it is over (the thread's pipe wakes the loop: one wake-up per transaction)."""
        loop = asyncio.get_running_loop()
        ax = self._ax
        if ax is None:
            ax = self._ax = xfer_runners.async_xfer_runner(self._proto._backend)
        assert self._fd is not None
        ax.submit(plan_of(self.port, self._fd, action))
        self._ax_call, self._ax_over = then, loop.create_future()
        if self._ax_loop is not loop:  # watched once per loop, until close
            if self._ax_loop is not None and not self._ax_loop.is_closed():
                self._ax_loop.remove_reader(ax.fd)
            loop.add_reader(ax.fd, self._xfer_done)
            self._ax_loop = loop

    def _xfer_done(self) -> None:
        ax = self._ax
        assert ax is not None
        r = ax.result()
        if r is None:
            return  # (a stale wake-up: still under way)
        then, over = self._ax_call, self._ax_over
        self._ax_call = self._ax_over = None
        if over is not None and not over.done():
            over.set_result(None)
        if then is not None:  # None: the transaction was cancelled meanwhile
            then(r)
        else:
            self._xfer_abandoned(r)

    def _xfer_abandoned(self, r: xfer.XferResult) -> None:
        """The report of an xfer whose transaction was cancelled: if its request
        went out, the protocol waits out the answer it may still get."""
        if r.sent:
            self._proto.abandoned_xfer(r.end, r.last_t if r.data else 0.0, _monotonic())

    async def _run_xfer(self, action: Xfer) -> xfer.XferResult:
        """An `Xfer` as this task's await."""
        fut: asyncio.Future[xfer.XferResult] = asyncio.get_running_loop().create_future()

        def then(r: xfer.XferResult) -> None:
            if not fut.done():
                fut.set_result(r)

        self._submit(action, then)
        try:
            return await fut
        except BaseException:
            self._cancel_xfer()
            raise

    def _cancel_xfer(self) -> None:
        """The transaction was cancelled: end its xfer under way (at once, with
        whatever it read; its report comes unheard)."""
        self._ax_call = None
        if self._ax_over is not None and self._ax is not None:
            self._ax.cancel()

    async def _xfer_over(self) -> None:
        """Wait for the end of an xfer a cancelled transaction left under way (it
        was cancelled, and ends at once): the port is the thread's until then."""
        over, ax = self._ax_over, self._ax
        if over is None or ax is None:
            return
        if over.get_loop() is asyncio.get_running_loop():
            await asyncio.shield(over)
            return
        # left by a loop that has ended (asyncio.run returned meanwhile): its reader
        # will not run; the thread's report comes all the same
        ax.cancel()
        while (r := ax.result()) is None:
            await asyncio.sleep(0.001)
        self._ax_call = self._ax_over = None
        self._xfer_abandoned(r)

    async def _run(self, call: Call) -> Any:
        async with self._lock:
            link = self._serial_link
            if self.port.closed:  # closed by the user, or it failed
                await self._ready(link)  # `PortError`, or the port reopened (`LinkRevival`)
            if link.port is not self._known_port:
                self._reopened()
            try:
                return await self._run_call(call)
            except PortError:
                link.failed()  # (its reader and timers are gone: the port may close)
                raise

    async def _ready(self, link: SerialLink) -> None:
        """`SerialLink.ready`; a reopen that waits on the network (an ``rtu+tcp://``
        connect) runs on a worker thread, not holding up the loop: a cancel leaves
        it to end there, and the next request (or `close`) waits for it."""
        loop = asyncio.get_running_loop()
        fut = self._reopening
        if fut is None or fut.done() or fut.get_loop() is not loop:
            if not (link.reopen_blocks and link.reopen_due()):
                link.ready()  # (no attempt due, or one that does not wait)
                return
            fut = self._reopening = loop.run_in_executor(None, link.ready)
        await asyncio.shield(fut)

    async def _reopen_over(self) -> None:
        """Wait for a reopen a cancelled request left on its worker thread (its port
        is closed with the master's, not left open after it)."""
        fut, self._reopening = self._reopening, None
        if fut is not None and not fut.done() and fut.get_loop() is asyncio.get_running_loop():
            with contextlib.suppress(Exception):
                await asyncio.shield(fut)

    def _reopened(self) -> None:
        """The link reopened its port after it failed: the new descriptor."""
        port = self._known_port = self.port
        self._fd = port.fd
        self._inflight = None  # (a thread read of the old port, failed with it)
        if self._fd is None and self._reader is None:
            self._reader = ThreadPoolExecutor(1, thread_name_prefix=f"pyrtu-read-{port.name}")

    async def _run_call(self, call: Call) -> Any:
        """One transaction on the open port (`_run` holds the lock)."""
        port = self.port
        if self._ax_over is not None:
            await self._xfer_over()
        proto = self._proto
        slave, pdu, decode = call
        proto.start(slave, pdu, decode, _monotonic())
        if self._fd is not None and not port.has_wire:
            # a repeated request is one Xfer, awaited by this task (one
            # wake-up); other steps run in the loop's callbacks (the first action,
            # SEND or QUIET, changes nothing: asked again there)
            first = proto.next_action(_monotonic(), True)
            if not isinstance(first, Xfer):
                return await self._run_callbacks(proto)
            return await self._run_task(proto, first)
        return await self._run_task(proto)

    async def _run_task(self, proto: ClientProtocol, action: Any = None) -> Any:
        """The protocol's actions as this task's loop (``action``: the first one,
        already asked for): a repeated request's `Xfer`, ports without a
        descriptor (thread reads) and real lines (the write's drain runs in an
        executor)."""
        try:
            xfer = self._fd is not None
            while True:
                if action is None:
                    action = proto.next_action(_monotonic(), xfer)
                if isinstance(action, Xfer):
                    report(self.port, proto, await self._run_xfer(action))
                    if proto.done:  # (the common end: the result without a Done)
                        return proto.result()
                elif isinstance(action, Wait):
                    data = await self._wait(action)
                    proto.wait_done(data, _monotonic())
                elif isinstance(action, Send):
                    start, end = await self._transmit(action.data)
                    proto.transmitted(end, start)
                else:
                    return action.result()
                action = None
        except BaseException:
            proto.abort(_monotonic())
            raise

    async def _run_callbacks(self, proto: ClientProtocol) -> Any:
        """The transaction driven by the loop's callbacks (descriptor ports without a
        wire: pseudo-terminals, virtual bus drops): each wake-up (the timer or the
        descriptor of a `Wait`) runs `_CallbackStepper.step` in the callback itself, and the
        awaiting task wakes once, when the transaction is over.  (The loop's
        ``time()`` is `time.monotonic`.)"""
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        stepper = _CallbackStepper(self, proto, fut)
        stepper.step()
        try:
            return await fut
        except BaseException:
            stepper.stop()
            self._cancel_xfer()
            proto.abort(_monotonic())
            raise

    # ------------------------------------------------------------- plumbing

    async def transact(
        self, req: Request[Any] | str, slave: Any, *args: Any, **kwargs: Any
    ) -> tuple[Any, float]:
        """As `pyrtu.Master.transact`: ``(value, end_time)`` of the request ``req``
        (the transactions of a multi-page request are separate: other callers may
        interleave)."""
        request = request_table.REQUESTS[req] if isinstance(req, str) else req
        if request.build is not None:  # one transaction: no plan to step through
            call = request_table.call_of(request, slave, args, kwargs, self._link.address)
            value, end = await self._transact(call)
            return (value if request.post is None else request.post(value)), end
        steps = self._steps(request, slave, args, kwargs)
        step = steps.next()
        while step is not None:
            step = steps.next(*await self._step(step))
        return steps.value, steps.end  # type: ignore[return-value]

    async def _step(self, step: Call | Rules) -> tuple[Any, float | None]:
        if isinstance(step, Rules):
            await self.add_rule(*step)
            return None, None
        return await self._transact(step)

    async def _transact(self, call: Call) -> tuple[Any, float]:
        if self._tcp is not None:
            return await self._tcp.transact(call)
        answer = await self._run(call)
        return answer, self._serial_link.end_of(call)

    async def connect(self) -> None:
        """Connect a ``tcp://`` master now rather than at its first request (a
        `PortError` when it cannot); nothing for a port opened already."""
        if self._tcp is not None:
            await self._tcp.connect()

    async def add_rule(
        self, function: int, request_rule: LengthRule | None, response_rule: LengthRule | None
    ) -> None:
        """Register length rules for a (vendor) function code in the framer."""
        async with self._lock:
            self._link.set_rules(function, request_rule, response_rule)

    async def close(self) -> None:
        """Close the port once the transaction in progress (if any) is over."""
        if self._tcp is not None:
            await self._tcp.close()
            return
        async with self._lock:
            await self._xfer_over()
            await self._reopen_over()
            if not self.port.closed:  # (a port that failed was closed then)
                await self._late_answer_over()
            self._close_now()

    async def _late_answer_over(self) -> None:
        """A cancelled transaction's answer may still be on the wire: wait it out
        (reading and discarding it) before the port goes to whoever opens it next,
        whose request would otherwise collide with it."""
        proto, fd = self._proto, self._fd
        while True:
            now = _monotonic()
            until = proto.late_answer_over_at()
            if until <= now:
                return
            await asyncio.sleep(min(until - now, proto.settle))
            if fd is not None:
                try:
                    data = read_now(self.port, fd)
                except PortError:
                    return  # the port is gone: no answer comes through it
                if data:
                    proto.receive_data(data, _monotonic())

    def _close_now(self) -> None:
        if self._ax is not None:
            if self._ax_loop is not None and not self._ax_loop.is_closed():
                self._ax_loop.remove_reader(self._ax.fd)
            self._ax.close()  # (idle: close waited for the xfer under way)
            self._ax = self._ax_loop = None
        self._serial_link.close()
        if self._reader is not None:
            self._reader.shutdown(wait=False, cancel_futures=True)

    async def __aenter__(self) -> AsyncMaster:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ---------------------------------------------------------------- requests
    # `pyrtu.Master`'s methods as coroutines, made from the one table of requests
    # (`pyrtu.pdu.requests.REQUESTS`, `_install` below); typed here for users' mypy.
    # fmt: off
    if TYPE_CHECKING:
        async def request(self, slave: int, pdu: bytes) -> bytes: ...
        async def exchange(self, slave: int, pdu: bytes) -> bytes: ...
        async def execute(self, slave: int, function: int, data: bytes = b"", *,
                          request_rule: LengthRule | None = None,
                          response_rule: LengthRule | None = None) -> bytes: ...
        async def read_coils(self, slave: int, address: int, count: int) -> list[bool]: ...
        async def read_discrete_inputs(self, slave: int, address: int,
                                       count: int) -> list[bool]: ...
        async def read_holding_registers(self, slave: int, address: int,
                                         count: int) -> list[int]: ...
        async def read_input_registers(self, slave: int, address: int,
                                       count: int) -> list[int]: ...
        async def write_coil(self, slave: int, address: int, value: bool) -> None: ...
        async def write_register(self, slave: int, address: int, value: int) -> None: ...
        async def write_coils(self, slave: int, address: int, values: Iterable[bool]) -> None: ...
        async def write_registers(self, slave: int, address: int,
                                  values: Iterable[int]) -> None: ...
        async def mask_write_register(self, slave: int, address: int, and_mask: int,
                                      or_mask: int) -> None: ...
        async def read_write_registers(self, slave: int, read_address: int, read_count: int,
                                       write_address: int, values: Iterable[int]) -> list[int]: ...
        async def read_exception_status(self, slave: int) -> int: ...
        async def diagnostics(self, slave: int, sub_function: int, data: int = 0) -> int: ...
        async def get_comm_event_counter(self, slave: int) -> tuple[int, int]: ...
        async def get_comm_event_log(self, slave: int) -> pdus.CommEventLog: ...
        async def report_server_id(self, slave: int) -> bytes: ...
        async def read_fifo_queue(self, slave: int, address: int) -> list[int]: ...
        async def read_file_record(self, slave: int,
                                   items: Sequence[tuple[int, int, int]]) -> list[list[int]]: ...
        async def write_file_record(self, slave: int,
                                    items: Sequence[tuple[int, int, Sequence[int]]]) -> None: ...
        async def read_device_identification(self, slave: int, read_code: int = 1,
                                             object_id: int = 0) -> dict[int, bytes]: ...
    # fmt: on


def _install(cls: type[AsyncMaster]) -> None:
    """The request methods of ``cls``: each is `AsyncMaster.transact` of its table
    entry, with the sync `pyrtu.Master` method's name, signature and docstring."""

    def method(req: Request[Any]) -> Any:
        build, post = req.build, req.post

        async def run(self: AsyncMaster, slave: Any, *args: Any, **kwargs: Any) -> Any:
            if build is not None:
                # one transaction (the hot path): `transact` without the answer's
                # end time, which the method does not return
                call = request_table.call_of(req, slave, args, kwargs, self._link.address)
                tcp = self._tcp
                value = await self._run(call) if tcp is None else await tcp.value(call)
                return value if post is None else post(value)
            return (await self.transact(req, slave, *args, **kwargs))[0]

        functools.update_wrapper(run, getattr(Master, req.name))
        run.__qualname__ = f"{cls.__name__}.{req.name}"
        return run

    for req in request_table.REQUESTS.values():
        setattr(cls, req.name, method(req))


_install(AsyncMaster)


class _CallbackStepper:
    """One transaction of an `AsyncMaster` driven from the loop's callbacks: the
    protocol's actions, where each `Wait` is a timer (and a reader when it
    listens) that calls `step` again."""

    __slots__ = (
        "_fd", "_fut", "_loop", "_master", "_needed", "_port", "_proto", "_reading", "_timer"
    )  # fmt: skip

    def __init__(self, master: AsyncMaster, proto: ClientProtocol, fut: asyncio.Future[Any]):
        self._master = master
        self._loop = fut.get_loop()
        self._port = master.port
        self._fd: int = master._fd  # type: ignore[assignment]
        self._proto = proto
        self._fut = fut
        self._timer: asyncio.TimerHandle | _ptimer.TimerHandle | None = None
        self._reading = False
        self._needed = 0  # the pending Wait's

    def stop(self) -> None:
        """Cancel the pending wait (the transaction ended or was cancelled)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._reading:
            self._reading = False
            self._loop.remove_reader(self._fd)

    def _wake(self) -> None:
        self.stop()
        if not self._fut.done():  # cancelled meanwhile: the task aborts the protocol
            self.step(self._needed)

    def _read(self, needed: int) -> None:
        """The read that ends a `Wait`: the bytes first where they are due, else a
        poll first (nothing is expected)."""
        port = self._port
        data = read_now(port, self._fd) if needed else port.read(0)
        self._proto.wait_done(data, _monotonic())

    def _xfer_done(self, r: xfer.XferResult) -> None:
        if self._fut.done():
            return  # cancelled meanwhile: the task aborted the protocol
        try:
            report(self._port, self._proto, r)
        except Exception as exc:  # PortError
            self._fail(exc)
            return
        self.step()

    def _fail(self, exc: Exception) -> None:
        self.stop()
        self._proto.abort(_monotonic())
        if not self._fut.done():
            self._fut.set_exception(exc)

    def step(self, woke: int | None = None) -> None:
        """Carry out the protocol's actions until one must wait or it is done;
        ``woke``: a wait just ended (its ``needed``: read what came first)."""
        proto, fd = self._proto, self._fd
        try:
            if woke is not None:
                self._read(woke)
            while True:
                action = proto.next_action(_monotonic(), True)
                if isinstance(action, Wait):
                    if action.until > _monotonic():
                        self._timer = _ptimer.call_at(self._loop, action.until, self._wake)
                        self._needed = action.needed
                        if action.listen:
                            self._reading = True
                            self._loop.add_reader(fd, self._wake)
                        return
                    self._read(action.needed)
                elif isinstance(action, Send):
                    start, end = self._port.write(action.data)
                    proto.transmitted(end, start)
                elif isinstance(action, Xfer):
                    self._master._submit(action, self._xfer_done)
                    return
                else:
                    assert isinstance(action, Done)
                    self._fut.set_result(action.result())
                    return
        except Exception as exc:  # the typed errors, PortError; the task re-raises
            self._fail(exc)


#: descriptors a ``select()`` loop is given at most (it takes those below 1024 only,
#: and scans every one at each wait)
SELECT_LIMIT = 256


def new_event_loop(descriptors: int = 0) -> asyncio.AbstractEventLoop:
    """An event loop whose timers have microsecond resolution.

    The default loop's epoll selector rounds every wait up to a whole millisecond;
    at 115200 baud t3.5 is 1.75 ms, so a rounded wait costs a large part of the
    line's capacity.  This loop waits in ``select()`` (microseconds; descriptors
    below 1024, plenty for a process with tens of ports).  ``descriptors``: how
    many ports and connections it will watch; beyond `SELECT_LIMIT` (a thousand
    ``tcp://`` devices), the default epoll loop, whose waits `pyrtu.drivers._ptimer`
    makes exact with a timerfd."""
    import selectors

    if descriptors > SELECT_LIMIT:
        return asyncio.new_event_loop()

    loop = asyncio.SelectorEventLoop(selectors.SelectSelector())
    _ptimer.mark_precise(loop)  # its own timers are exact: no timerfd
    return loop


def run(main: Any, *, debug: bool | None = None, descriptors: int = 0) -> Any:
    """``asyncio.run(main)`` on `new_event_loop` (microsecond timers; ``descriptors``:
    as there), with this thread's timer slack shrunk to 1 µs (Linux; the default
    50 µs of slack is a large part of t3.5 at high baud rates)."""
    tighten_this_thread()
    if sys.version_info >= (3, 11):
        factory = functools.partial(new_event_loop, descriptors)
        with asyncio.Runner(debug=debug, loop_factory=factory) as runner:
            return runner.run(main)
    loop = new_event_loop(descriptors)  # Python 3.10: what asyncio.Runner does, by hand
    try:
        asyncio.set_event_loop(loop)
        if debug is not None:
            loop.set_debug(debug)
        return loop.run_until_complete(main)
    finally:
        pending = asyncio.all_tasks(loop)
        for task in pending:
            task.cancel()
        loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        loop.run_until_complete(loop.shutdown_asyncgens())
        asyncio.set_event_loop(None)
        loop.close()


from pyrtu.drivers.aio_slave import AsyncSlave  # noqa: E402  (the server side, re-exported)

__all__ = ["AsyncMaster", "AsyncSlave", "new_event_loop", "run"]
