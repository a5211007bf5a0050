"""Many Modbus TCP client connections behind one descriptor: the poller's
``tcp://`` buses at C speed (docs/many-devices.md).

A `TcpMux` holds up to ``capacity`` connected sockets and is driven from the
event loop's thread (no thread of its own, nothing in it waits; time is its
clock's, ``time.monotonic``).  `TcpMux.submit` sends one request on one of them;
`TcpMux.fd` is readable when any of them is (``loop.add_reader``), and then
`TcpMux.service` reads them all (C: csrc/rtu_mux_io.c, one call; the twin:
pyrtu/tcp/_pymux.py, a selector), each answer whole by its MBAP length, drops
late answers, judges unit and function and ends each transaction whose timeout
passed (`TcpMux.deadline` says when to call it for that); `TcpMux.take` hands
the ended ones over as `MuxDone` records.  `pyrtu.tcp.mux_backends.open_mux`
makes one.  One transaction per connection is in
flight at a time.

`TcpMux.repeat` is a poll's steady state: the connection's request sent again
by `TcpMux.service` every interval, so the event loop makes no call to send it.

So polling a thousand devices costs the event loop one wake-up per batch of
answers, not a task, a timer and a transport callback per device.
"""

from __future__ import annotations

import socket
from typing import NamedTuple, Protocol

from pyrtu.drivers.xfer import TCP_CLOSED, TCP_ERRNO, TCP_TIMEOUT

#: `MuxDone.flags` (csrc/rtu_mux.h RTU_MUX_*): the connection still repeats its
#: request when the record is taken
REPEATING = 1
#: ... the transaction was sent by the repeat, not by `TcpMux.submit`
RESENT = 2


class MuxDone(NamedTuple):
    """One ended transaction (csrc/rtu_mux.h rtu_mux_done)."""

    token: int
    """the submitter's"""
    conn: int
    """the connection (`TcpMux.attach`'s number)"""
    status: int
    """`pyrtu.drivers.xfer`'s TCP_ANSWER, TCP_EXCEPTION, TCP_MISMATCH, TCP_TIMEOUT,
    TCP_CLOSED, TCP_ERRNO (``err`` at ``stage``) or TCP_BAD_HEADER (``err``: the
    `pyrtu.core.mbap.MBAP_ERROR_BY_CODE` index); after an answer, ``err`` non-zero
    says an invalid header followed it"""
    err: int
    stage: int
    late: int
    """late answers (of earlier transactions) dropped before this one's"""
    tid: int
    start: float
    """when the send began (monotonic seconds)"""
    end: float
    """when the read that completed the answer returned (or the timeout came)"""
    adu: bytes
    """the answer's unit id and PDU (empty without an answer)"""
    flags: int = 0
    """`REPEATING` and `RESENT` (`TcpMux.repeat`)"""

    @property
    def broken(self) -> bool:
        """Whether the connection can carry no other transaction."""
        return self.status in (TCP_CLOSED, TCP_ERRNO) or (
            self.status != TCP_TIMEOUT and self.err != 0
        )


def refused(conn: int, tid: int, unit: int, pdu: bytes, timeout: float) -> ValueError:
    """`TcpMux.submit`'s error, in the same words on both backends."""
    return ValueError(
        f"the mux refused the request (connection {conn}, tid {tid}, unit {unit}, "
        f"{len(pdu)}-byte PDU, timeout {timeout!r}): a bad argument, or a connection "
        "not attached or still in a transaction"
    )


def refused_repeat(conn: int, first: float, interval: float) -> ValueError:
    """`TcpMux.repeat`'s error, in the same words on both backends."""
    return ValueError(
        f"the mux refused to repeat connection {conn} (first {first!r}, interval "
        f"{interval!r}): a bad interval, a connection not attached, one with no "
        "request since, a broadcast, or one whose record is not taken"
    )


class MuxError(OSError):
    """The mux's descriptor failed (its ``epoll`` refused): no answer comes."""


class TcpMux(Protocol):
    """The connections behind one descriptor (see the module docstring)."""

    @property
    def fd(self) -> int:
        """Readable when an attached socket is: then call `service`."""
        ...

    def attach(self, sock: socket.socket) -> int:
        """A connected socket (made non-blocking, kept until `detach`): its number;
        ValueError when all ``capacity`` are attached."""
        ...

    def detach(self, conn: int) -> None:
        """Forget connection ``conn`` and close its socket: its transaction in flight
        ends with no record, its record not yet taken is dropped."""
        ...

    def submit(
        self,
        conn: int,
        token: int,
        tid: int,
        unit: int,
        pdu: bytes,
        timeout: float,
        awaited: bool = True,
    ) -> bool:
        """Send ``pdu`` to ``unit`` as transaction ``tid`` on ``conn``; its record comes
        within ``timeout`` seconds (``awaited`` False: a broadcast, its record once
        it is sent, TCP_ANSWER with no answer).  True: it ended already and its
        record waits for `take` (the send failed, the connection failed while it
        was idle, a broadcast went out: `fd` does not become readable for it).
        ValueError (nothing sent) for a bad
        argument, a connection not attached, or one whose transaction is not over
        and taken."""
        ...

    def repeat(self, conn: int, first: float, interval: float) -> None:
        """Send ``conn``'s request (its last `submit`'s, awaited) again from
        ``first`` on, every ``interval`` seconds (1 ns to 2**60 ns), from `service`:
        at the first service at or after its due time once the transaction before
        has ended and its record is taken; the next is due one ``interval`` after
        that due time, or at once when that is more than an interval behind (the
        poller's beat, `pyrtu.poller.schedule.BusScheduler.next_request`).  Each
        is a new transaction (the next transaction id, the submit's token and
        timeout), its record flagged `RESENT`.  A plain answer (TCP_ANSWER,
        nothing late, no error) keeps the repeat going; any other end of a
        transaction ends it, as `submit` and `detach` do.  ValueError
        (nothing changed) for a bad interval, a connection not attached, one
        with no request since it was attached, a broadcast, or one whose record
        is not taken."""
        ...

    def unrepeat(self, conn: int) -> bool:
        """End ``conn``'s repeat, if any: True when a transaction is in flight or
        its record is not taken (it still comes, without `REPEATING`), False when
        the connection is idle.  ValueError for a connection not attached."""
        ...

    def service(self) -> int:
        """Read what the ready sockets hold, end the transactions due and send the
        repeats due; how many records wait for `take` (MuxError when the
        descriptor failed)."""
        ...

    def deadline(self) -> float | None:
        """When `service` is next needed: the first transaction in flight times
        out, or an idle connection's repeat is due (monotonic seconds; None:
        neither)."""
        ...

    def take(self) -> list[MuxDone]:
        """The ended transactions not taken yet, in the order they ended."""
        ...

    @property
    def services(self) -> int:
        """`service` calls so far (the benchmark's wake-ups)."""
        ...

    def close(self) -> None:
        """Detach and close every socket, and the descriptor."""
        ...


__all__ = [
    "REPEATING",
    "RESENT",
    "MuxDone",
    "MuxError",
    "TcpMux",
    "refused",
    "refused_repeat",
]
