"""`Poller`: the asyncio driver of the bus schedulers, and its thread for scripts.

::

    async with Poller(load_config("points.toml")) as poller:
        async for update in poller.updates():
            print(update.name, update.value, update.time)

    with Poller(config).running() as poller:      # a background thread
        time.sleep(1)
        print(poller.values())
        poller.write("pump.reference", 30.0)

One asyncio task per bus runs its `BusScheduler` against a master (`AsyncMasterLike`:
``transact`` and ``close``); buses run concurrently, each one transaction at a time.
Every value is stamped with the time (``time.time()`` clock) the answer's last byte
arrived; `updates` and `on_update` deliver changes only (beyond each point's
deadband), `events` and `on_event` also port up/down, slave online/offline, dropped
points and overload.

A port that fails (not opened or connected, a drop unplugged, a TCP peer gone) is
reported once (`PortState`, one log line), closed and reopened on the back-off of
`pyrtu.drivers.reconnect` (``backoff`` doubling to ``max_backoff``) while the other
buses poll on; what failed because the port did is not counted against the slaves.

Network buses (``tcp://``, ``rtu+tcp://``...) connect within the bounds of the
configuration's `ConnectLimits` (``[connect]``: connects in progress at once in
the poller and per host, the pace of the start, the jitter of the reconnects;
`pyrtu.poller.connect`, docs/many-devices.md): each is opened by its own task,
the ``rank``-th one ``rank / start_rate`` seconds after the start (its polls take
that phase), so a thousand devices neither connect nor poll in one burst.  Their
polls wake on a grid of ``lateness`` (2.5 %) of the bus's shortest interval (at
most 25 ms, `wake_tick`): the buses due within one tick share one wake-up of the
loop.  The plain ``tcp://`` ones run on the poller's mux (`pyrtu.poller.muxdrive`).

A bus task that raises anything else (a fault of the poller itself) is supervised
(`pyrtu.drivers.supervise`): logged once with its cause, reported (`TaskFailed`),
counted (the bus's ``task_failures`` in `summary`), the transaction it was in
failed (a write or read waiting on it gets the error; a poll block stays in the
schedule) and the task started again on the bus's back-off; the other buses poll on.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable, Iterable, Sequence
from functools import partial
from typing import Any

from pyrtu.core._closing import AsyncService
from pyrtu.drivers.reconnect import Backoff, Reconnect
from pyrtu.drivers.supervise import TaskFailure, supervise
from pyrtu.pdu.codecs import apply_masks
from pyrtu.pdu.errors import ExceptionResponseError, PortError

from .busrun import BusRun
from .config import Bus, ConfigError, Device, PollerConfig, load_config, make_config
from .connect import LATENESS, ConnectGate, ConnectLimits, network_host
from .events import (
    BusReport,
    Event,
    PortState,
    SlaveStats,
    TaskFailed,
    Tracker,
    Unchanged,
    Update,
)
from .masters import BY_FUNCTION, FACTORIES, AsyncMasterLike, is_port_error, open_master
from .muxdrive import MuxDriver, collect_tick, on_mux
from .points import Point, Value, encode_point, encode_point_value
from .schedule import BusScheduler, ScheduledRequest
from .thread import PollerThread

log = logging.getLogger("pyrtu.poller")

MasterFactory = Callable[[Bus], AsyncMasterLike]
_QUEUE = 65536


def describe_port(ev: PortState) -> str:
    """A `PortState` for people (the log line and the command line's message)."""
    if ev.up:
        return (f"bus {ev.bus}: port {ev.port} back after {ev.time - ev.since:.1f} s "
                f"({ev.attempts} failed attempt{'s' if ev.attempts != 1 else ''})")  # fmt: skip
    return f"bus {ev.bus}: port {ev.port} down: {ev.error} (retrying with back-off)"


def describe_task_failed(ev: TaskFailed) -> str:
    """A `TaskFailed` for people (the log line and the command line's message)."""
    return f"bus {ev.bus}: task {ev.task} failed: {ev.error} (restarting in {ev.retry_in:.2f} s)"


def wake_tick(interval: float, lateness: float = LATENESS) -> float:
    """The grid the polls of a network bus whose shortest interval is ``interval``
    wake on: ``lateness`` (`ConnectLimits.lateness`, 2.5 %) of it, of a second at
    most (25 ms).  Its polls keep their beat (each is due an interval after the
    last was due) and are at most a tick late; a thousand devices at 1 Hz, started
    a millisecond apart, wake the loop forty times a second rather than a thousand
    (each wake-up costs tens of microseconds, and a batch of answers is cheaper
    per answer than one alone: docs/many-devices.md)."""
    return lateness * min(interval, 1.0)


def _samples(ev: Event | Unchanged) -> list[Event | Unchanged]:
    """``ev`` as the events it stands for: an `Unchanged` block's `Update` events."""
    out: list[Event | Unchanged] = []
    if isinstance(ev, Unchanged):
        out += ev.updates()
    else:
        out.append(ev)
    return out


class Poller(AsyncService):
    """Keeps declared points fresh on many buses (see the module docstring).

    ``config``: a `PollerConfig` (`load_config`, `make_config`) or a TOML path;
    or ``buses``/``points``/``devices`` directly.  ``master``: ``"auto"`` (the
    default: the plain ``tcp://`` buses on the poller's mux, `pyrtu.poller.muxdrive`,
    one descriptor for all of them, csrc/rtu_mux_io.c; the others as ``"aio"``),
    ``"aio"`` (`pyrtu.drivers.aio.AsyncMaster` on every bus), ``"thread"`` (a sync
    `pyrtu.Master` on a worker thread per bus) or a function ``Bus -> master``.
    ``changes_only``: deliver a value only when it changed beyond its deadband.
    ``connect``: how network buses connect (None: the configuration's
    ``[connect]``, `ConnectLimits`' defaults without one).
    """

    def __init__(
        self,
        config: PollerConfig | str | None = None,
        *,
        buses: Iterable[Bus] = (),
        points: Iterable[Point] = (),
        devices: Iterable[Device] = (),
        master: MasterFactory | str = "auto",
        changes_only: bool = True,
        connect: ConnectLimits | None = None,
    ) -> None:
        if isinstance(config, str):
            config = load_config(config)
        if config is None:
            config = make_config(buses, points, devices)
        elif not isinstance(config, PollerConfig):
            raise TypeError(f"config must be a PollerConfig or a path, not {type(config).__name__}")
        else:
            config.check()
        self.config = config
        self.changes_only = changes_only
        if connect is not None and not isinstance(connect, ConnectLimits):
            raise TypeError(f"connect must be ConnectLimits, not {type(connect).__name__}")
        self.connect_limits = connect if connect is not None else config.connect
        self._gate = ConnectGate(self.connect_limits)
        self._auto = master == "auto"
        self._mux: MuxDriver | None = None
        if isinstance(master, str):
            if master not in ("auto", *FACTORIES):
                raise ValueError(
                    f"master must be one of auto, {', '.join(FACTORIES)}, not {master!r}"
                )
            self._factory: MasterFactory = FACTORIES["aio" if self._auto else master]
        else:
            self._factory = master
        self._points = {p.name: p for p in config.points}
        self._tracker = Tracker()
        self._update_cbs: list[Callable[[Update], None]] = []
        self._event_cbs: list[Callable[[Event], None]] = []
        self._subscribers: list[tuple[asyncio.Queue[Event | None], bool]] = []
        self._runs: dict[str, BusRun] = {}
        self._running = False
        self._t0 = time.monotonic()
        self._offset = time.time() - time.monotonic()
        self._updates = 0
        self._values_read = 0
        self._lost_events = 0
        # (bus, slave) that answered FC 22 with exception 1, and their read-modify-writes
        self._no_mask_write: set[tuple[str, int]] = set()
        self._rmw_locks: dict[tuple[str, int], asyncio.Lock] = {}
        self._make_schedulers()

    def _make_schedulers(self) -> None:
        now = time.monotonic()
        by_bus: dict[str, list[Point]] = {}
        for p in self.config.points:
            by_bus.setdefault(p.bus, []).append(p)
        for bus in self.config.buses:
            mine = by_bus.get(bus.name, [])
            # the silence timer: a transaction's wait for its answer, every attempt
            wait = float(bus.master.get("timeout", 1.0)) * (1 + int(bus.master.get("retries", 0)))
            try:
                sched = BusScheduler(
                    bus.name, mine, bus.wire(), self.config.limits(bus.name), bus.limits,
                    share=bus.share, offline_after=bus.offline_after, backoff=bus.backoff,
                    max_backoff=bus.max_backoff, stamp_offset=self._offset, now=now,
                    timeout=wait,
                )  # fmt: skip
            except ValueError as e:
                raise ConfigError(f"{self.config.source}: bus {bus.name!r}: {e}") from None
            host = network_host(bus.port)
            jitter = Backoff.jitter if host is None else self.connect_limits.jitter
            backoff = Backoff(initial=bus.backoff, maximum=bus.max_backoff, jitter=jitter)
            run = self._runs[bus.name] = BusRun(bus, sched, Reconnect(backoff), host=host)
            run.on_mux = self._auto and on_mux(bus)
            if host is not None and mine:
                run.tick = wake_tick(min(p.interval for p in mine), self.connect_limits.lateness)

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        """Open every local bus's master and start polling.  A port that cannot be
        opened is a `PortState` event and is retried with back-off while the other
        buses poll; any other error of a master (a wrong keyword) is raised, and
        the ports opened so far are closed again.  A network bus is opened and
        connected by its own task at its place in the staggered start (what fails
        there is a port failure, reported and retried)."""
        if self._running:
            return
        now = time.monotonic()
        self._gate = ConnectGate(self.connect_limits)  # (its semaphores: this loop's)
        rank = 0
        for run in self._runs.values():
            run.wake = asyncio.Event()
            run.reconnect = Reconnect(run.reconnect.backoff)
            run.worked, run.values, run.task_failures = False, 0, 0
            run.start_at = now
            if run.host is not None:  # opened by its task, at its rank of the start
                run.start_at = now + self.connect_limits.start_offset(rank)
                run.sched.start_at(run.start_at)
                rank += 1
        self._running = True
        try:
            mine = [run for run in self._runs.values() if run.on_mux]
            if mine:
                self._mux = MuxDriver(self, len(mine), collect_tick(r.tick for r in mine))
            for run in self._runs.values():
                if run.host is None:
                    await self._open(run)
        except BaseException:
            self._running = False
            await self._close_masters()
            await self._close_mux()
            raise
        self._t0 = now
        for run in self._runs.values():
            run.sched.reset_stats(now)
            run.task = supervise(
                f"pyrtu-poll-{run.bus.name}",
                partial(self._run_bus, run),
                partial(self._task_failed, run),
                backoff=run.reconnect.backoff,
                running=lambda: self._running,
            )

    async def stop(self) -> None:
        """Stop polling and close the masters; pending writes fail with
        CancelledError; iterators end.  Returns within about one timeout of the
        buses (a transaction in progress on a thread master is waited for)."""
        self._running = False
        for run in self._runs.values():
            run.wake.set()
        tasks = {r.task for r in self._runs.values() if r.task is not None}
        # cancel until they end: a cancellation can be lost (Python 3.11's
        # asyncio.wait_for returns the result of an inner future that completed at
        # the same moment), and the bus loop also ends on _running being False
        pending = tasks
        while pending:
            for t in pending:
                t.cancel()
            _, pending = await asyncio.wait(pending, timeout=0.05)
        for t in tasks:
            if not t.cancelled() and t.exception() is not None:
                log.error("poller task %s failed", t.get_name(), exc_info=t.exception())
        for run in self._runs.values():
            run.task = None
            for fut in run.pending.values():
                if not fut.done():
                    fut.cancel()
            run.pending.clear()
        await self._close_masters()
        await self._close_mux()
        for q, _ in self._subscribers:
            self._put(q, None)

    async def _close_masters(self) -> None:
        await asyncio.gather(*(self._close_master(r) for r in self._runs.values()))

    async def _close_mux(self) -> None:
        mux, self._mux = self._mux, None
        if mux is not None:
            await mux.close()

    async def _close_master(self, run: BusRun) -> None:
        """Close the bus's master, waiting at most its timeout and a second (a
        transaction a thread master is in the middle of ends within its timeout)."""
        master, run.master = run.master, None
        if master is None:
            return
        closing = asyncio.ensure_future(master.close())
        limit = float(run.bus.master.get("timeout", 1.0)) + 1.0
        done, _ = await asyncio.wait({closing}, timeout=limit)
        if not done:
            closing.cancel()
            log.warning("bus %s: closing the port took more than %.1f s", run.bus.name, limit)
        elif closing.exception() is not None:  # closing a vanished port
            log.info("bus %s: close: %s", run.bus.name, closing.exception())

    async def run(self, duration: float | None = None) -> None:
        """Start, poll for ``duration`` seconds (None: until cancelled), stop."""
        await self.start()
        try:
            if duration is None:
                await asyncio.Event().wait()
            else:
                await asyncio.sleep(duration)
        finally:
            await self.stop()

    @property
    def descriptors(self) -> int:
        """The ports and connections the poller opens (one per bus): what picks
        its event loop (`pyrtu.drivers.aio.new_event_loop`: the buses on the mux
        are watched through one descriptor, but their sockets' numbers count
        against a select() loop's limit all the same)."""
        return len(self._runs)

    def running(self) -> PollerThread:
        """The poller on a background thread (a context manager with sync methods)."""
        return PollerThread(self)

    # ------------------------------------------------------------------ the bus loop

    async def _run_bus(self, run: BusRun) -> None:
        if run.on_mux:
            await self._run_mux_bus(run)
            return
        sched = run.sched
        clock = time.monotonic
        while self._running:
            master = run.master
            if master is None:
                await self._reopen(run)
                continue
            now = clock()
            req = sched.next_request(now)
            if req is None:
                await self._nap_until(run, sched.deadline())
                continue
            fut = run.pending.pop(req.tag, None) if req.tag else None
            run.inflight, run.inflight_future = req, fut
            events: list[Event] | list[Event | Unchanged]
            due = sched.offline_due(req)
            timer = None if due is None else asyncio.get_running_loop().call_later(
                max(0.0, due - clock()), self._silent, run, req)  # fmt: skip
            try:
                data, answered = await master.transact(BY_FUNCTION[req.function], *self._args(req))
            except asyncio.CancelledError:
                # abandoned, not failed: nothing counts, the block or probe stays due
                # (a probe left "in flight" would never be sent after a restart)
                sched.on_port_failure(req)
                if fut is not None and not fut.done():
                    fut.cancel()
                raise
            except Exception as exc:
                if fut is not None and not fut.done():
                    fut.set_exception(exc)
                if is_port_error(exc):
                    sched.on_port_failure(req)
                    await self._port_failed(run, exc)
                    continue
                end = clock()
                self._port_ok(run, end)
                events = sched.on_failure(req, exc, end)
            else:
                self._port_ok(run, clock())
                end = answered
                events = sched.on_response(req, data, end)
                if fut is not None and not fut.done():
                    fut.set_result(data)
            finally:
                if timer is not None:
                    timer.cancel()
            run.inflight = run.inflight_future = None
            if events:
                self._dispatch(events, run)

    async def _run_mux_bus(self, run: BusRun) -> None:
        """A bus on the mux: open and connect it, then let the mux drive its
        transactions until its connection fails (`MuxDriver.drive`)."""
        while self._running:
            if run.master is None:
                await self._reopen(run)
                continue
            assert self._mux is not None
            error = await self._mux.drive(run)
            await self._port_failed(run, error)

    def _task_failed(self, run: BusRun, failure: TaskFailure) -> None:
        """The bus task raised: count it; the first failure of a run is logged (with
        the traceback at debug level) and reported (`TaskFailed`); the transaction it
        was in is failed (its poll block stays due)."""
        run.task_failures += 1
        req, fut = run.inflight, run.inflight_future
        run.inflight = run.inflight_future = None
        if fut is not None and not fut.done():
            fut.set_exception(failure.error)
        if req is not None:
            try:
                run.sched.on_port_failure(req)
            except Exception:  # the schedule itself is what fails: the log says so
                log.exception("bus %s: putting back %r failed", run.bus.name, req)
        log.debug("bus %s: task %s failed", run.bus.name, failure.task, exc_info=failure.error)
        if failure.first:
            now = time.time()
            self._dispatch([TaskFailed(run.bus.name, failure.task, failure.cause,
                                       failure.retry_in, now)])  # fmt: skip

    def _silent(self, run: BusRun, req: ScheduledRequest) -> None:
        """``req`` still unanswered at `BusScheduler.offline_due`: its slave is offline."""
        self._dispatch(run.sched.on_silence(req, time.monotonic()))

    async def _nap_until(self, run: BusRun, deadline: float | None) -> None:
        """`_nap` until ``deadline`` (monotonic seconds; None: until woken), a
        network bus's rounded up to its `wake_tick` grid: the buses due within one
        tick wake together (one wake-up of the loop, not one each)."""
        if deadline is None:
            await self._nap(run, None)
            return
        await self._nap(run, run.wake_at(deadline) - time.monotonic())

    async def _nap(self, run: BusRun, delay: float | None) -> None:
        """Sleep ``delay`` seconds (None: until woken), or until a submit or `stop`
        wakes the bus."""
        run.wake.clear()
        if not self._running:
            return
        if delay is None:
            await run.wake.wait()
        elif delay > 0:
            # a timer that sets the event, not asyncio.wait_for (which makes a task
            # per wait: measured 130 against 70 us of CPU)
            timer = asyncio.get_running_loop().call_later(delay, run.wake.set)
            try:
                await run.wake.wait()
            finally:
                timer.cancel()

    async def _open(self, run: BusRun) -> None:
        """Open the bus's master; a port that fails begins (or continues) an outage.
        Other errors are raised while the poller starts, and count as port failures
        once it runs (a bus task never dies of them).  A network bus's open and
        connect hold a slot of the `ConnectGate` (its host's and the poller's)."""
        try:
            if run.host is None:
                run.master = await open_master(self._factory, run.bus)
                return
            async with self._gate.slot(run.host):
                factory = self._factory
                if run.on_mux:
                    assert self._mux is not None
                    factory = self._mux.open
                run.master = await open_master(factory, run.bus)
                connect = getattr(run.master, "connect", None)
                if connect is not None:  # (a master that connects at its first request)
                    await connect()
        except Exception as exc:
            if not (is_port_error(exc) or run.task is not None):
                raise
            await self._port_failed(run, exc)

    async def _reopen(self, run: BusRun) -> None:
        """While the port is down: fail the writes and reads asked meanwhile, wait
        for the back-off, then try to open the port again.  A network bus's first
        open waits for its place in the start (the writes asked meanwhile wait)."""
        while self._running:
            now = time.monotonic()
            if run.reconnect.down:
                self._fail_urgent(run)
            wait = max(run.reconnect.wait(now), run.start_at - now)
            if wait <= 0:
                break
            await self._nap(run, wait)
        if self._running:
            await self._open(run)

    def _fail_urgent(self, run: BusRun) -> None:
        outage = run.reconnect.outage
        error = "the port is down" if outage is None else f"the port is down: {outage.error}"
        for req in run.sched.take_urgent():
            fut = run.pending.pop(req.tag, None)
            if fut is not None and not fut.done():
                fut.set_exception(PortError(run.port, error))

    async def _port_failed(self, run: BusRun, exc: BaseException) -> None:
        """The port failed: close it; the first failure of an outage is reported
        (one `PortState` event, one log line), the next attempts are not."""
        now = time.monotonic()
        text = (str(exc) or type(exc).__name__).removeprefix(f"{run.port}: ")
        if run.reconnect.failed(now, text):
            outage = run.reconnect.outage
            assert outage is not None
            off = self._offset
            ev = PortState(run.bus.name, run.port, False, outage.error, outage.since + off,
                           outage.attempts, now + off)  # fmt: skip
            self._dispatch([ev])
        await self._close_master(run)

    def _port_ok(self, run: BusRun, now: float) -> None:
        """A transaction went through the port (answered or not): an outage ends."""
        run.worked = True
        if run.reconnect.down:
            outage = run.reconnect.recovered(now)
            assert outage is not None
            off = self._offset
            ev = PortState(run.bus.name, run.port, True, outage.error, outage.since + off,
                           outage.attempts, now + off)  # fmt: skip
            self._dispatch([ev])

    @staticmethod
    def _args(req: ScheduledRequest) -> tuple[Any, ...]:
        if req.kind == "write":
            if req.function == 22:  # mask write: the and and or masks
                return (req.slave, req.address, *req.values)
            if len(req.values) == 1 and req.function in (5, 6):
                return (req.slave, req.address, req.values[0])
            return (req.slave, req.address, list(req.values))
        return (req.slave, req.address, req.count)

    def _dispatch(self, events: Sequence[Event | Unchanged], run: BusRun | None = None) -> None:
        """Deliver ``events``; ``run``: the bus whose scheduler made them all (its
        updates counted once for the batch, not per value).  An `Unchanged` block is
        noted as read, no value of it delivered, when only changes are; otherwise
        its samples are delivered as the block's `Update` events would be."""
        now = time.monotonic()
        offer, changes_only, runs = self._tracker.offer, self.changes_only, self._runs
        update_cbs = self._update_cbs
        read = 0
        if not changes_only and any(type(ev) is Unchanged for ev in events):
            events = [u for ev in events for u in _samples(ev)]
        for ev in events:
            if isinstance(ev, Unchanged):  # (only changes delivered: none of these changed)
                read += len(ev.points)  # (a scheduler's: with its bus's run)
                self._tracker.reread(ev.points, now, ev.time)
                continue
            if isinstance(ev, Update):
                read += 1
                if run is None:
                    runs[ev.point.bus].values += 1
                if not offer(ev, now) and changes_only:
                    continue
                self._updates += 1
                for cb in update_cbs:
                    self._call(cb, ev)
            elif isinstance(ev, PortState):
                log.warning("%s", describe_port(ev))
            elif isinstance(ev, TaskFailed):
                log.error("%s", describe_task_failed(ev))
            else:
                log.info("%s", ev)
            for ecb in self._event_cbs:
                self._call(ecb, ev)
            for q, only_updates in self._subscribers:
                if not only_updates or isinstance(ev, Update):
                    self._put(q, ev)
        self._values_read += read
        if run is not None:
            run.values += read

    def _put(self, q: asyncio.Queue[Event | None], ev: Event | None) -> None:
        if q.full():  # a consumer that does not keep up loses the oldest events
            q.get_nowait()
            self._lost_events += 1
        q.put_nowait(ev)

    @staticmethod
    def _call(cb: Callable[[Any], None], ev: Any) -> None:
        try:
            cb(ev)
        except Exception:
            log.exception("poller callback %r failed", cb)

    # ------------------------------------------------------------------ output

    def on_update(self, callback: Callable[[Update], None]) -> None:
        """Call ``callback(update)`` for every delivered value (in the loop's thread)."""
        self._update_cbs.append(callback)

    def on_event(self, callback: Callable[[Event], None]) -> None:
        """Call ``callback(event)`` for every event: delivered updates, `PortState`,
        `SlaveState`, `PointDropped`, `Overload`, `TaskFailed`."""
        self._event_cbs.append(callback)

    async def updates(self) -> AsyncIterator[Update]:
        """The delivered values, as they come (ends when the poller stops)."""
        async for ev in self._subscribe(True):
            assert isinstance(ev, Update)
            yield ev

    async def events(self) -> AsyncIterator[Event]:
        """Every event, as it comes (ends when the poller stops)."""
        async for ev in self._subscribe(False):
            yield ev

    async def _subscribe(self, only_updates: bool) -> AsyncIterator[Event]:
        q: asyncio.Queue[Event | None] = asyncio.Queue(_QUEUE)
        entry = (q, only_updates)
        self._subscribers.append(entry)
        try:
            while True:
                ev = await q.get()
                if ev is None:
                    return
                yield ev
        finally:
            self._subscribers.remove(entry)

    def values(self) -> dict[str, Value | None]:
        """The last value read of every point read so far."""
        return {k: u.value for k, u in self._tracker.latest().items()}

    def latest(self) -> dict[str, Update]:
        """The last update of every point read so far (value and time)."""
        return self._tracker.latest()

    def age(self, name: str) -> float | None:
        """Seconds since point ``name`` was last read (None: never)."""
        self.point(name)
        return self._tracker.age(name, time.monotonic())

    def point(self, name: str) -> Point:
        try:
            return self._points[name]
        except KeyError:
            raise KeyError(f"no point named {name!r}") from None

    def report(self) -> list[BusReport]:
        now = time.monotonic()
        return [r.sched.report(now) for r in self._runs.values()]

    def slave_stats(self) -> list[SlaveStats]:
        return [s for r in self._runs.values() for _, s in sorted(r.sched.slave_stats().items())]

    def scheduler(self, bus: str) -> BusScheduler:
        return self._runs[bus].sched

    def summary(self) -> dict[str, Any]:
        """Per-bus utilisation, load and port state, per-slave counts and state, the
        points dropped, and the events lost by iterators that did not keep up
        (JSON-ready).  ``updates``: the values delivered (change-only unless
        ``changes_only=False``); ``values_read``: every value read."""
        now = time.monotonic()
        dropped = {n for r in self._runs.values() for n in r.sched.dropped}
        return {
            "summary": True,
            "seconds": round(now - self._t0, 3),
            "updates": self._updates,
            "values_read": self._values_read,
            "points": len(self._points),
            "points_read": len(self._tracker),
            "points_unread": sum(
                1 for n in self._points if self._tracker.last(n) is None and n not in dropped
            ),
            "buses": self.bus_summary(now),
            "slaves": [s.as_dict() for s in self.slave_stats()],
            "dropped_points": sorted(dropped),
            "lost_events": self._lost_events,
        }

    def bus_summary(self, now: float | None = None) -> list[dict[str, Any]]:
        """Each bus's part of `summary`: its `BusReport` with the port (its state,
        outages, last error), the values read and the task failures."""
        now = time.monotonic() if now is None else now
        buses = []
        for run in self._runs.values():
            doc = run.sched.report(now).as_dict()
            outage = run.reconnect.outage
            doc.update(port=run.port, port_state=run.port_state(), outages=run.reconnect.outages,
                       port_error=None if outage is None else outage.error,
                       values_read=run.values, task_failures=run.task_failures)  # fmt: skip
            buses.append(doc)
        return buses

    def health(self) -> list[str]:
        """What keeps the poller from polling, one line each (empty: it polls): not
        started or stopped, a bus task that no longer runs, a port down."""
        if not self._running:
            return ["the poller is not running"]
        problems = []
        for run in self._runs.values():
            if run.task is None or run.task.done():
                problems.append(f"bus {run.bus.name}: its task is not running")
            outage = run.reconnect.outage
            if run.reconnect.down and outage is not None:
                problems.append(f"bus {run.bus.name}: port {run.port} down: {outage.error}")
        return problems

    def on_latency(self, callback: Callable[[str, int, float], None] | None) -> None:
        """Call ``callback(bus, slave, seconds)`` for every answered transaction
        (a response or an exception response; one callback: None removes it), as it
        completes, in the loop's thread: what latency histograms observe."""
        for run in self._runs.values():
            run.sched.observe = None if callback is None else partial(callback, run.bus.name)

    def last(self, name: str) -> Update | None:
        """The last update of point ``name`` (None: not read yet)."""
        self.point(name)
        return self._tracker.last(name)

    def points_read(self) -> int:
        """How many points were read at least once."""
        return len(self._tracker)

    def port_state(self, bus: str) -> str:
        """``up``, ``down`` (an outage is on: the poller retries) or ``unknown``
        (nothing went through the port yet)."""
        return self._run_of(bus).port_state()

    def reset_stats(self) -> None:
        now = time.monotonic()
        self._t0 = now
        self._updates = 0
        self._values_read = 0
        for r in self._runs.values():
            r.values = 0
            r.sched.reset_stats(now)

    # ------------------------------------------------------------------ writes, reads

    def _check_running(self) -> None:
        if not self._running:
            raise RuntimeError("the poller is not running (start it first)")

    def _submit(self, run: BusRun, reqs: Sequence[ScheduledRequest]) -> list[asyncio.Future[Any]]:
        loop = asyncio.get_running_loop()
        futs = []
        for r in reqs:
            fut: asyncio.Future[Any] = loop.create_future()
            run.pending[r.tag] = fut
            futs.append(fut)
        run.wake.set()
        if self._mux is not None and run.on_mux:
            self._mux.kick(run)
        return futs

    async def write(self, name: str, value: object) -> str:
        """Write ``value`` to point ``name`` (scale and offset undone, an enum's label
        encoded), ahead of every poll on its bus; raises what the transaction raised
        (ValueError, nothing sent, when the point cannot take the value).  Returns
        how: ``"write"`` (FC 05/06/15/16); a ``bit`` or ``bits`` point, the rest of
        its register kept: ``"mask_write"`` (FC 22), or ``"read_modify_write"`` (FC 03
        then FC 06) on a slave that answered FC 22 with exception 1 (illegal
        function), remembered for the rest of the run."""
        p = self.point(name)
        encoded = encode_point_value(p, value)
        self._check_running()
        run = self._runs[p.bus]
        if encoded.mask is None:
            req = run.sched.submit_write(p.slave, p.table, p.address, encoded.words)
            (fut,) = self._submit(run, [req])
            await fut
            return "write"
        and_mask, or_mask = encoded.mask
        slave = (p.bus, p.slave)
        if slave not in self._no_mask_write:
            req = run.sched.submit_mask_write(p.slave, p.address, and_mask, or_mask)
            (fut,) = self._submit(run, [req])
            try:
                await fut
                return "mask_write"
            except ExceptionResponseError as e:
                if e.code != 1:
                    raise
                self._no_mask_write.add(slave)
                log.info(
                    "bus %s slave %d: FC 22 refused (illegal function): bits and fields are"
                    " written by read-modify-write",
                    p.bus,
                    p.slave,
                )
        lock = self._rmw_locks.setdefault(slave, asyncio.Lock())
        async with lock:  # no other read-modify-write of this slave in between
            futs = self._submit(run, run.sched.submit_read(p.slave, "holding", p.address, 1))
            (current,) = await futs[0]
            new = apply_masks(int(current), and_mask, or_mask)
            req = run.sched.submit_write(p.slave, "holding", p.address, [new])
            (fut,) = self._submit(run, [req])
            await fut
        return "read_modify_write"

    async def write_registers(
        self, bus: str, slave: int, table: str, address: int, values: Sequence[int | bool]
    ) -> None:
        """Write raw ``values`` (FC 05/06/15/16) ahead of every poll on ``bus``."""
        run = self._run_of(bus)
        self._check_running()
        (fut,) = self._submit(run, [run.sched.submit_write(slave, table, address, values)])
        await fut

    async def read(self, name: str) -> Value | None:
        """Read point ``name`` now, ahead of every poll on its bus."""
        p = self.point(name)
        self._check_running()
        run = self._runs[p.bus]
        (fut,) = self._submit(run, run.sched.submit_read(p.slave, p.table, p.address, p.size))
        data = await fut
        return p.decode(data, p.address)

    async def read_registers(
        self, bus: str, slave: int, table: str, address: int, count: int
    ) -> list[int] | list[bool]:
        """Read ``count`` registers (or bits) now, ahead of every poll on ``bus``."""
        run = self._run_of(bus)
        self._check_running()
        futs = self._submit(run, run.sched.submit_read(slave, table, address, count))
        out: list[Any] = []
        for f in futs:
            out += await f
        return out

    def _run_of(self, bus: str) -> BusRun:
        try:
            return self._runs[bus]
        except KeyError:
            raise ValueError(f"bus: no bus named {bus!r}") from None


__all__ = ["MasterFactory", "Poller", "PollerThread", "describe_port", "encode_point"]
