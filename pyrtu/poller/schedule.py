"""The scheduler of one bus, sans-I/O: time is an input, nothing here waits.

A driver asks `BusScheduler.next_request(now)` for what to send, performs it, and
reports the outcome with `on_response(request, data, now)` or
`on_failure(request, error, now)` (``now``: when the answer's last byte arrived, or
when the transaction gave up); when nothing is due it sleeps until `deadline()`
(or until a write is submitted).  The order:

1. writes and on-demand reads (`submit_write`, `submit_read`), first come first served;
2. a confirmation: after a failed transaction of an online slave, that slave's
   earliest-due block, at once (even before its due time);
3. a probe of an offline slave whose back-off has run out;
4. the poll block with the earliest due time, if it is due.

Every transaction's wire-busy time is counted (from `next_request` to the end of
the answer or the timeout, plus the part of the mandatory t3.5 silence that
passed before `next_request`), so the scheduler knows the bus's utilisation; the
wire time each block needs per second (from the frame lengths, character time,
t3.5 and the slave's measured turnaround) sums to the bus's *load*: above 1 the
configured rates exceed the wire, an `Overload` event says so and names the
points that lag.

Slave health (docs/POLLER.md): ``offline_after`` consecutive failed transactions
(no answer, or garbage) take a slave offline (`SlaveState` event); after each
failure the slave's next block goes next (a confirmation), so the failures are
back to back.  With ``timeout`` (the master's, per transaction) a slave that is
asked ``offline_after`` times and silent for ``offline_after`` x ``timeout`` from
the end of its first unanswered request is offline then, while the last request
is still waiting for its answer: the driver arms `offline_due` and calls
`on_silence`; a late answer brings it back at once.  Offline, its blocks leave
the schedule and one short request probes it, after a back-off that doubles from
``backoff`` (0.5 s) to ``max_backoff`` (1 s: a slave that comes back is found
within about a second), never less than what keeps the probes within ``share`` of
the bus time while another slave of the bus is online.  Any answer, even an
exception, brings it back online with its blocks due at once; but not a
gateway's exception 0x0A or 0x0B (path unavailable, target device failed to
respond: `ExceptionResponseError.no_device_answered`), which says the slave did
not answer and counts as a timeout.  Exception 2 on a block splits it in two and
remembers the cut; on a single point it drops the point (`PointDropped`, once).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable, Iterable, Mapping, Sequence

from pyrtu.pdu.errors import ExceptionResponseError, FrameError, NoResponseError

from ._schedule_parts import (
    _WRITE_FUNCTIONS,
    POLL,
    PROBE,
    READ,
    WRITE,
    ScheduledRequest,
    _Health,
    _Stats,
    _Task,
)
from .events import (
    BusReport,
    Event,
    Overload,
    PointDropped,
    SlaveState,
    SlaveStats,
    Unchanged,
    Update,
)
from .plan import FUNCTIONS, Block, Cuts, Limits, Wire, chunks, gaps, plan, split
from .points import Point

#: the first wait before probing an offline slave (and before reopening a failed port)
BACKOFF = 0.5
#: the longest wait: a slave (or a port) that comes back is found within about a
#: second, where a back-off grown to 30 s hid it for up to 30 s after it was back
#: (each probe is one short request, and the share floor below keeps them cheap)
MAX_BACKOFF = 1.0


class BusScheduler:
    """Earliest-deadline-first scheduling of one bus's points (module docstring)."""

    def __init__(
        self,
        bus: str,
        points: Iterable[Point],
        wire: Wire,
        limits: Mapping[int, Limits] | None = None,
        default_limits: Limits | None = None,
        *,
        share: float = 0.05,
        offline_after: int = 3,
        backoff: float = BACKOFF,
        max_backoff: float = MAX_BACKOFF,
        stamp_offset: float = 0.0,
        timeout: float | None = None,
        now: float = 0.0,
    ) -> None:
        if not 0 < share <= 1:
            raise ValueError(f"share must be in (0, 1], not {share!r}")
        if isinstance(offline_after, bool) or not isinstance(offline_after, int):
            raise ValueError(f"offline_after must be a positive integer, not {offline_after!r}")
        if offline_after < 1:
            raise ValueError(f"offline_after must be a positive integer, not {offline_after!r}")
        if not 0 < backoff <= max_backoff:
            raise ValueError(f"backoff must be > 0 and <= max_backoff, not {backoff!r}")
        if timeout is not None and not timeout > 0:
            raise ValueError(f"timeout must be > 0 seconds (or None), not {timeout!r}")
        #: a transaction's response timeout (all its attempts): the silence timer
        self.timeout = timeout
        #: called with (slave, seconds) for every answered transaction (a response or
        #: an exception response): the latency histograms of ``--metrics``
        self.observe: Callable[[int, float], None] | None = None
        self.bus = bus
        self.wire = wire
        self.share = float(share)
        self.offline_after = offline_after
        self.backoff = float(backoff)
        self.max_backoff = float(max_backoff)
        self.stamp_offset = stamp_offset
        self._limits = dict(limits or {})
        self._default = default_limits or Limits()
        self._points: list[Point] = []
        for p in points:
            if p.bus != bus:
                raise ValueError(f"point {p.name!r} is on bus {p.bus!r}, not {bus!r}")
            most = self.limits(p.slave).per_request(p.table)
            if p.size > most:
                raise ValueError(
                    f"point {p.name!r} takes {p.size} registers; slave {p.slave} "
                    f"reads at most {most} per request"
                )
            self._points.append(p)
        self._cuts = Cuts()
        self._dropped: set[str] = set()
        self._tasks: list[_Task] = []
        self._heap: list[tuple[float, int, _Task]] = []
        self._seq = itertools.count()
        self._tags = itertools.count(1)
        self._urgent: list[ScheduledRequest] = []
        self._confirm: int | None = None  # the slave whose failure is to be confirmed
        self._health: dict[int, _Health] = {}
        self._offline_count = 0  # how many of them are offline (none: no probe to look for)
        self._stats = _Stats()
        self._overloaded = False
        self._load = 0.0
        self._since_check = 0
        self._prev_end: float | None = None
        self._ended = 0  # transactions ended (never reset: back-to-back failures)
        for p in self._points:
            self._slave(p.slave)
        for slave, h in self._health.items():
            mine = sorted(
                (p for p in self._points if p.slave == slave), key=lambda p: (p.size, p.address)
            )
            if mine:
                h.probe = (mine[0].table, mine[0].address)
        self._replan(self._points, now)

    # ------------------------------------------------------------------ set-up

    def limits(self, slave: int) -> Limits:
        return self._limits.get(slave, self._default)

    def _slave(self, slave: int) -> _Health:
        h = self._health.get(slave)
        if h is None:
            h = self._health[slave] = _Health()
            self._stats.slaves[slave] = SlaveStats(self.bus, slave)
        return h

    def _replan(self, points: Sequence[Point], due: float) -> None:
        by_slave: dict[int, list[Point]] = {}
        for p in points:
            if p.name not in self._dropped:
                by_slave.setdefault(p.slave, []).append(p)
        for slave, mine in sorted(by_slave.items()):
            for block in plan(mine, self.wire, self.limits(slave), self._cuts):
                self._add_task(block, due)

    def _add_task(self, block: Block, due: float) -> None:
        task = _Task(block, due, self._cost(block))
        task.frames = self.wire.read(block.table, block.count, 0.0)
        task.function = block.function
        task.suspended = self._slave(block.slave).offline
        self._tasks.append(task)
        if not task.suspended:
            self._push(task)

    def _push(self, task: _Task) -> None:
        task.seq = next(self._seq)
        heapq.heappush(self._heap, (task.due, task.seq, task))

    def _cost(self, block: Block) -> float:
        ta = self._slave(block.slave).turnaround
        return self.wire.read(block.table, block.count, ta)

    @property
    def blocks(self) -> list[Block]:
        """The blocks in the schedule (offline slaves' included)."""
        return [t.block for t in self._tasks if t.alive]

    # ------------------------------------------------------------------ requests

    def submit_write(
        self, slave: int, table: str, address: int, values: Sequence[int | bool]
    ) -> ScheduledRequest:
        """Queue a write (ahead of every poll): one value -> FC 05/06, several ->
        FC 15/16.  Returns the request; its outcome comes back through
        `on_response`/`on_failure` like any other."""
        if table not in ("coils", "holding"):
            raise ValueError(f"table: only coils and holding registers are writable, not {table!r}")
        vals = tuple(values)
        if not vals:
            raise ValueError("values: nothing to write")
        fn = _WRITE_FUNCTIONS[(table, len(vals) == 1)]
        req = ScheduledRequest(
            WRITE, slave, table, address, len(vals), fn, vals, tag=next(self._tags)
        )
        # request ADU: FC 05/06 slave, function, address, value, CRC (8 bytes); FC 15/16
        # also a quantity and a byte count (9 bytes) and the packed values
        size = len(vals) * 2 if table == "holding" else (len(vals) + 7) // 8
        req.cost = self.wire.frames(8 if len(vals) == 1 else 9 + size, 8)
        self._urgent.append(req)
        return req

    def submit_mask_write(
        self, slave: int, address: int, and_mask: int, or_mask: int
    ) -> ScheduledRequest:
        """Queue FC 22 (Mask Write Register, Application Protocol 6.16) of a holding
        register ahead of every poll; its outcome comes back like a write's."""
        vals = (and_mask, or_mask)
        req = ScheduledRequest(WRITE, slave, "holding", address, 1, 22, vals, tag=next(self._tags))
        req.cost = self.wire.frames(10, 10)  # slave, 22, address, masks, CRC; echoed
        self._urgent.append(req)
        return req

    def submit_read(
        self, slave: int, table: str, address: int, count: int
    ) -> list[ScheduledRequest]:
        """Queue an on-demand read (ahead of every poll), split within the slave's
        maximum per request; returns the requests in address order."""
        if table not in FUNCTIONS:
            raise ValueError(f"table: must be one of {', '.join(FUNCTIONS)}, not {table!r}")
        out = []
        for a, n in chunks(table, address, count, self.limits(slave)):
            req = ScheduledRequest(READ, slave, table, a, n, FUNCTIONS[table], tag=next(self._tags))
            req.cost = self.wire.read(table, n)
            out.append(req)
        self._urgent.extend(out)
        return out

    def next_request(self, now: float) -> ScheduledRequest | None:
        """What to send now, or None when nothing is due before `deadline`."""
        if self._stats.started is None:
            self._stats.started = now
        if self._urgent:
            req = self._urgent.pop(0)
            req.issued = now
            return req
        if self._confirm is not None:
            task = self._confirmation()
            if task is not None:
                return self._issue(task, now)
        probe = self._due_probe(now)
        if probe is not None:
            return probe
        heap = self._heap
        while heap:
            due, seq, task = heap[0]
            if not task.alive or task.suspended or seq != task.seq:
                heapq.heappop(heap)
                continue
            if due > now:
                return None
            heapq.heappop(heap)
            return self._issue(task, now)
        return None

    def _confirmation(self) -> _Task | None:
        """The block that confirms the last failure: the failing slave's earliest
        due one waiting in the schedule (taken out of the heap: its entry goes
        stale)."""
        slave, self._confirm = self._confirm, None
        best: _Task | None = None
        for task in self._tasks:
            if (task.block.slave == slave and task.alive and not task.suspended
                    and task.seq >= 0 and (best is None or task.due < best.due)):  # fmt: skip
                best = task
        if best is not None:
            best.seq = -1  # out of the heap (in flight) until requeued
        return best

    def _issue(self, task: _Task, now: float) -> ScheduledRequest:
        self._advance(task, now)
        b = task.block
        return ScheduledRequest(POLL, b.slave, b.table, b.address, b.count, task.function, (), b,
                       issued=now, cost=task.cost, task=task)  # fmt: skip

    @staticmethod
    def _advance(task: _Task, now: float) -> None:
        """``task``'s block goes out at ``now``: its beat moves on (one interval from
        when it was due, or from now when that is more than an interval behind)
        and it is in flight, out of the schedule (its heap entry stale)."""
        due, interval = task.due, task.block.interval
        task.late = max(0.0, now - due)
        if due > now:  # a confirmation ahead of its time: the beat starts again from now
            task.due = now + interval
        else:
            nxt = due + interval
            task.due = now if nxt + interval < now else nxt
        task.seq = -1

    def steady(self, req: ScheduledRequest) -> bool:
        """Whether ``req``, a poll just issued, can be sent again at each of its
        block's due times without this scheduler choosing (`repeated`: the
        steady state the ``tcp://`` mux keeps in C, `pyrtu.tcp.mux.TcpMux.repeat`):
        its block is the only one in the schedule and nothing else is waiting (no
        write or read queued, no failure to confirm, no slave offline)."""
        task = req.task
        return (
            req.kind == POLL
            and task is not None
            and not self._urgent
            and self._confirm is None
            and not self._offline_count
            and all(t is task or not t.alive for t in self._tasks)
        )

    def repeated(self, req: ScheduledRequest, start: float) -> None:
        """``req``'s block was sent again at ``start`` (by the mux's repeat, not
        through `next_request`): issued then, its beat moved on as `next_request`
        moves it; its outcome comes through `on_response` or `on_failure` as any
        request's."""
        task = req.task
        if task is None:
            raise ValueError("repeated: only a poll block's request is repeated")
        req.issued = start
        self._advance(task, start)
        self._drop_stale()  # (its entry from the outcome before, stale now, goes)

    def _drop_stale(self) -> None:
        """The heap's top entries that are no longer due dropped: a block gone, or
        suspended (its slave offline), or issued since it was pushed."""
        heap = self._heap
        while heap and (
            not heap[0][2].alive or heap[0][2].suspended or heap[0][1] != heap[0][2].seq
        ):
            heapq.heappop(heap)

    def _due_probe(self, now: float) -> ScheduledRequest | None:
        if not self._offline_count:
            return None
        best: tuple[float, int] | None = None
        for slave, h in self._health.items():
            if h.offline and not h.probing and h.probe_due <= now:
                if best is None or h.probe_due < best[0]:
                    best = (h.probe_due, slave)
        if best is None:
            return None
        slave = best[1]
        h = self._health[slave]
        h.probing = True
        table, address = h.probe
        return ScheduledRequest(PROBE, slave, table, address, 1, FUNCTIONS[table], issued=now,
                       cost=self.wire.read(table, 1))  # fmt: skip

    def deadline(self) -> float | None:
        """The earliest time `next_request` has something (None: never, until a
        submit); at or before now when something is ready."""
        if self._urgent or self._confirm is not None:
            return float("-inf")
        best: float | None = None
        self._drop_stale()
        heap = self._heap
        if heap:
            best = heap[0][0]
        if not self._offline_count:
            return best
        for h in self._health.values():
            if h.offline and not h.probing and (best is None or h.probe_due < best):
                best = h.probe_due
        return best

    # ------------------------------------------------------------------ outcomes

    def _end(self, req: ScheduledRequest, now: float) -> float:
        """Count a finished transaction; returns its latency (issue to end)."""
        latency = max(0.0, now - req.issued)
        # only what falls inside the statistics' window counts (a transaction in
        # flight when the window started counts from its start)
        stats = self._stats
        start = stats.started
        issued = req.issued if start is None else max(req.issued, start)
        busy = max(0.0, now - issued)
        # the silence of t3.5 after the previous frame is wire time too: the part of
        # it that passed before this request was issued is not inside ``busy`` (none
        # on TCP, where t3.5 is 0)
        t35 = self.wire.t35
        if t35 and self._prev_end is not None:
            after = self._prev_end if start is None else max(self._prev_end, start)
            busy += min(t35, max(0.0, issued - after))
        self._prev_end = now
        self._ended += 1
        stats.busy += busy
        stats.transactions += 1
        st = stats.slaves.get(req.slave)
        if st is None:
            self._slave(req.slave)
            st = stats.slaves[req.slave]
        st.requests += 1
        st.busy += busy
        return latency

    def _requeue(self, req: ScheduledRequest) -> None:
        task = req.task
        if task is not None and task.alive and not task.suspended:
            self._push(task)

    def on_response(
        self, req: ScheduledRequest, data: Sequence[int] | Sequence[bool] | None, now: float
    ) -> list[Event | Unchanged]:
        """A transaction answered (``data``: the registers or bits read; None for a
        write).  Returns the events: an `Update` for every point of a poll block
        (or, when the block answered exactly what it answered last time, one
        `Unchanged` for them all: nothing decoded), `SlaveState` when the slave
        comes back, `Overload` when the bus's state changes."""
        busy = self._end(req, now)
        h = self._health[req.slave]
        st = self._stats.slaves[req.slave]
        st.responses += 1
        st.note_latency(busy)
        if self.observe is not None:
            self.observe(req.slave, busy)
        self._turnaround(req, busy, h)
        back = self._back(req, h, st, now)
        came_back = bool(back)  # (a SlaveState: the load is checked now)
        events: list[Event | Unchanged] = []
        events += back
        if req.kind == POLL and req.block is not None and data is not None:
            b = req.block
            stamp = now + self.stamp_offset
            dropped, address = self._dropped, b.address
            points = b.points if not dropped else [p for p in b.points if p.name not in dropped]
            task = req.task
            if task is not None and task.raw == data:
                events.append(Unchanged(tuple(points), data, address, stamp))
            else:
                if task is not None:
                    task.raw = data
                events += [Update(p, p.decode(data, address), stamp) for p in points]
            self._requeue(req)
        self._check_load(now, events, came_back)
        return events

    def _turnaround(self, req: ScheduledRequest, busy: float, h: _Health) -> None:
        if req.kind == WRITE:
            return
        task = req.task
        frames = task.frames if task is not None else self.wire.read(req.table, req.count, 0.0)
        ta = max(0.0, busy - frames)
        h.turnaround = ta if h.turnaround is None else 0.9 * h.turnaround + 0.1 * ta

    def _back(self, req: ScheduledRequest, h: _Health, st: SlaveStats, now: float) -> list[Event]:
        h.failures = 0
        h.probing = False
        h.backoff = 0.0
        h.silent_from = h.silenced = None
        was = st.online
        st.online = True
        if not h.offline:
            return [] if was else [SlaveState(self.bus, req.slave, True, now + self.stamp_offset)]
        h.offline = False
        self._offline_count -= 1
        for task in self._tasks:
            if task.alive and task.block.slave == req.slave and task.suspended:
                task.suspended = False
                task.due = now
                self._push(task)
        return [SlaveState(self.bus, req.slave, True, now + self.stamp_offset)]

    def on_failure(self, req: ScheduledRequest, error: BaseException, now: float) -> list[Event]:
        """A transaction failed: an exception response (`ExceptionResponseError`),
        no answer (`NoResponseError`), a bad answer (`FrameError`), or anything else
        (counted as no answer; a failed port is `on_port_failure`'s).  A gateway's
        0x0A or 0x0B (`ExceptionResponseError.no_device_answered`) is no answer of
        the slave: a timeout, towards ``offline_after``."""
        busy = self._end(req, now)
        h = self._health[req.slave]
        st = self._stats.slaves[req.slave]
        events: list[Event] = []
        if isinstance(error, ExceptionResponseError) and not error.no_device_answered:
            st.exceptions += 1
            st.note_latency(busy)
            if self.observe is not None:
                self.observe(req.slave, busy)
            self._turnaround(req, busy, h)
            events += self._back(req, h, st, now)
            if req.kind == POLL and error.code == 2 and req.block is not None:
                events += self._hole(req.block, now)
            else:
                self._requeue(req)
            self._check_load(now, events)
            return events
        if isinstance(error, FrameError) and not isinstance(error, NoResponseError):
            st.frame_errors += 1
        else:
            st.timeouts += 1
            if isinstance(error, NoResponseError) and not h.offline and self.timeout:
                # its timeout ran from the end of the request: that end is at or
                # before ``now - timeout`` (so the timer never cuts a window short);
                # the silence counts from the first of back-to-back failures only
                if h.silent_from is None or h.last_fail != self._ended - 1:
                    h.silent_from = now - self.timeout
                h.last_fail = self._ended
        h.failures += 1
        if h.offline and req is h.silenced:
            # in flight when on_silence took the slave offline: the first probe waits
            # as it would have after this failure (its wire time keeps the share)
            h.silenced = None
            h.probe_due = max(h.probe_due, now + self._probe_gap(req.slave, self.backoff, busy))
        elif h.offline:
            h.probing = False
            h.backoff = min(self.max_backoff, max(self.backoff, 2 * h.backoff))
            h.probe_due = now + self._probe_gap(req.slave, h.backoff, busy)
        elif h.failures >= self.offline_after:
            events.append(self._offline(req.slave, h, st, busy, now))
        else:
            self._requeue(req)
            self._confirm = req.slave
        self._check_load(now, events)
        return events

    def _offline(self, slave: int, h: _Health, st: SlaveStats, busy: float, now: float) -> Event:
        h.offline = True
        self._offline_count += 1
        h.silent_from = None
        st.online = False
        h.backoff = self.backoff
        h.probe_due = now + self._probe_gap(slave, self.backoff, busy)
        self._confirm = None if self._confirm == slave else self._confirm
        for task in self._tasks:
            task.suspended = task.suspended or task.block.slave == slave
        return SlaveState(self.bus, slave, False, now + self.stamp_offset)

    def _probe_gap(self, slave: int, backoff: float, busy: float) -> float:
        """The wait before the next probe of offline ``slave`` after a failed
        transaction that held the bus ``busy`` seconds: its back-off, and never less
        than what keeps its probes within ``share`` of the bus time while another
        slave of the bus is online (with no one else to poll, a probe delays no one)."""
        others = any(not h.offline for s, h in self._health.items() if s != slave)
        return max(backoff, busy * (1 / self.share - 1)) if others else backoff

    def offline_due(self, req: ScheduledRequest) -> float | None:
        """When ``req``'s slave goes offline if ``req`` is still unanswered (then the
        driver calls `on_silence`): ``offline_after`` x ``timeout`` after the end of
        the first of ``offline_after`` requests in a row (no other transaction
        between) to a silent slave; None if ``req`` is not such a last request."""
        h = self._health.get(req.slave)
        if (h is None or h.offline or h.silent_from is None or self.timeout is None
                or h.failures < self.offline_after - 1 or h.last_fail != self._ended):  # fmt: skip
            return None
        return h.silent_from + self.offline_after * self.timeout

    def on_silence(self, req: ScheduledRequest, now: float) -> list[Event]:
        """``req`` is unanswered at its `offline_due`: its slave goes offline now; its
        outcome is still to come (an answer brings the slave back at once)."""
        h, due = self._health.get(req.slave), self.offline_due(req)
        if h is None or due is None or now < due:
            return []
        h.silenced = req
        return [self._offline(req.slave, h, self._stats.slaves[req.slave], 0.0, now)]

    def on_port_failure(self, req: ScheduledRequest) -> None:
        """The port failed during ``req`` (a drop unplugged, a TCP connection lost):
        the slave is not to blame, so nothing counts against it (no timeout, no
        failure towards ``offline_after``).  A poll block keeps its place in the
        schedule and a probe is due again; a write or read is the driver's to fail.
        The same for a transaction abandoned (the driver stopped during it)."""
        h = self._health.get(req.slave)
        if h is not None and req is h.silenced:
            h.silenced = None
        if req.kind == PROBE:
            if h is not None:
                h.probing = False
        elif req.kind == POLL:
            self._requeue(req)

    def take_urgent(self) -> list[ScheduledRequest]:
        """Take the queued writes and on-demand reads out (to fail them while the
        port is down)."""
        out, self._urgent = self._urgent, []
        return out

    def _hole(self, block: Block, now: float) -> list[Event]:
        """Exception 2 on ``block``: split it and learn the cut (`Cuts.learn`), or
        drop its point (and withdraw the cuts learned with it, `Cuts.forget_point`);
        then plan the slave's table again if a cut was withdrawn."""
        for task in self._tasks:
            if task.block is block:
                task.alive = False
        halves = split(block)
        out: list[Event] = []
        if halves is None:
            withdrawn: list[int] = []
            for p in block.points:
                if p.name not in self._dropped:
                    self._dropped.add(p.name)
                    withdrawn += self._cuts.forget_point(self.bus, p.slave, p.table, p.address)
                    out.append(
                        PointDropped(
                            p, "exception 2 (ILLEGAL DATA ADDRESS)", now + self.stamp_offset
                        )
                    )
        else:
            cut = halves[1].address
            withdrawn = self._cuts.learn(block, cut, proven=gaps(block) == 1)
        self._tasks = [t for t in self._tasks if t.alive]
        if withdrawn:
            # plan the slave's whole table again: blocks may merge across a withdrawn cut
            mine = [
                t
                for t in self._tasks
                if t.block.slave == block.slave and t.block.table == block.table
            ]
            for t in mine:
                t.alive = False
            self._tasks = [t for t in self._tasks if t.alive]
            points = [p for t in mine for p in t.block.points] + list(block.points)
            self._replan(points, now)
        elif halves is not None:
            self._replan(list(block.points), now)
        return out

    # ------------------------------------------------------------------ figures

    def _check_load(
        self, now: float, events: list[Event] | list[Event | Unchanged], state: bool | None = None
    ) -> None:
        """Every 16 transactions, and when a slave's state changed (``state``; None:
        a `SlaveState` among ``events``), an `Overload` event when the bus's load
        crossed 1."""
        self._since_check += 1
        if state is None:
            state = any(isinstance(e, SlaveState) for e in events)
        if self._since_check < 16 and not state:
            return
        self._since_check = 0
        load = self.load()
        over = load > 1.0
        if over != self._overloaded:
            self._overloaded = over
            events.append(Overload(self.bus, over, load, self.lagging(), now + self.stamp_offset))

    def load(self) -> float:
        """Wire seconds per second the online slaves' blocks need at their intervals."""
        total = 0.0
        for t in self._tasks:
            if t.alive and not t.suspended:
                t.cost = self._cost(t.block)
                total += t.cost / t.block.interval
        self._load = total
        return total

    def lagging(self) -> tuple[str, ...]:
        """Points whose block started more than one interval late last time."""
        return tuple(
            p.name
            for t in self._tasks
            if t.alive and not t.suspended and t.late > t.block.interval
            for p in t.block.points
        )

    def utilisation(self, now: float) -> float:
        """Wire-busy time over wall time since the statistics started."""
        s = self._stats
        span = 0.0 if s.started is None else max(0.0, now - s.started)
        return min(1.0, s.busy / span) if span > 0 else 0.0

    @property
    def last_load(self) -> float:
        """The load as last computed (every 16 transactions and on slave changes):
        what a display refreshed often reads, at no cost per block."""
        return self._load

    def report(self, now: float) -> BusReport:
        s = self._stats
        span = 0.0 if s.started is None else max(0.0, now - s.started)
        load = self.load()
        return BusReport(
            self.bus, self.utilisation(now), load, load > 1.0, self.lagging(), s.transactions, span
        )

    def slave_stats(self) -> dict[int, SlaveStats]:
        return dict(self._stats.slaves)

    def online(self, slave: int) -> bool | None:
        st = self._stats.slaves.get(slave)
        return None if st is None else st.online

    @property
    def dropped(self) -> frozenset[str]:
        return frozenset(self._dropped)

    def start_at(self, when: float) -> None:
        """Make every poll block first due at ``when`` (its beat from then on): a
        network bus's place in a staggered start."""
        for task in self._tasks:
            task.due = when
        self._heap = [(when, seq, task) for _, seq, task in self._heap]
        heapq.heapify(self._heap)

    def reset_stats(self, now: float) -> None:
        """Start the utilisation and the counts again from ``now``."""
        self._stats.started = now
        self._stats.busy = 0.0
        self._stats.transactions = 0
        for slave, old in self._stats.slaves.items():
            self._stats.slaves[slave] = SlaveStats(self.bus, slave, online=old.online)


__all__ = [
    "BACKOFF",
    "MAX_BACKOFF",
    "POLL",
    "PROBE",
    "READ",
    "WRITE",
    "BusScheduler",
    "ScheduledRequest",
]
