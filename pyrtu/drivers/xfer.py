"""One master xfer on a serial descriptor: what the drivers hand an `XferRunner` and
what it reports (C: csrc/rtu_xfer_io.c through pyrtu/drivers/_cxfer.py; the twin:
pyrtu/drivers/_pyxfer.py; `pyrtu.drivers.xfer_runners` picks the one of a backend).

The client protocol decides every time and length (`pyrtu.protocol.client_actions.
Xfer`); an xfer runner carries them out in one call: sleep to the send time, look
for stale input (then nothing is sent), write the request, sleep to the first read,
read the rest as it comes (all but the last character slept through), until the
answer's length (an exception answer's shorter one) or the deadline.  With nothing
awaited (``expect`` 0) it is a write at a time: a slave's response at the end of its
turnaround (`pyrtu.protocol.server.Reply` handed out ahead).  Times are monotonic
seconds (``time.monotonic``'s clock).
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol

from pyrtu.protocol.client_actions import Xfer

#: how an xfer ended (`XferResult.status`)
ANSWER, STALE, SHORT, ERRNO, GONE, CANCELLED = range(6)
#: where an ERRNO xfer failed (`XferResult.stage`)
STAGE_WRITE, STAGE_READ = 1, 2
#: bytes an xfer reads at most (an answer is at most 256; the rest is noise)
CAPACITY = 4096
#: `XferPlan.spin` at most (seconds; RTU_XFER_SPIN_MAX)
SPIN_MAX = 0.001


class XferResult(NamedTuple):
    """What an xfer saw."""

    status: int
    """ANSWER (the expected bytes came; with none expected, the request went), STALE
    (input was pending at the send time: nothing sent, `data` holds it), SHORT (the
    deadline, or a signal, with fewer bytes), ERRNO (`err` at `stage`), GONE (the
    descriptor reported input but gave none), CANCELLED (`AsyncXferRunner.cancel`)"""
    sent: bool
    """the request was written"""
    start: float
    """when the write began"""
    end: float
    """when its transmission ended"""
    data: bytes
    """what was read: the answer, or the stale input"""
    first_n: int
    """``data[:first_n]`` came in the first read of the answer"""
    first_t: float
    """when that read returned"""
    last_t: float
    """when the last read returned"""
    err: int
    """the errno of ERRNO"""
    stage: int
    """where ERRNO happened: STAGE_WRITE, STAGE_READ"""
    reads: int
    """the reads that returned bytes"""


class XferPlan(NamedTuple):
    """One xfer: the protocol's `Xfer` (the request, its times, the answer's
    length) on a port."""

    fd: int
    """the serial port's descriptor"""
    drain: bool
    """tcdrain after the write (a real line, not a pty)"""
    char: float
    """one character's time on the line (seconds)"""
    xfer: Xfer
    """what the protocol decided: ``data`` written at ``send_at``, the first read
    ``first_wake`` and the deadline ``timeout`` seconds after the end of
    transmission, ``expect`` the answer's length (0: none awaited, a slave's
    response), ``short_len`` an exception answer's (0: none)"""
    look: bool = True
    """input pending at the send time is stale and nothing is sent (a master)"""
    spin: float = 0.0
    """the last seconds before ``send_at`` waited on the clock instead of slept (at
    most `SPIN_MAX`): a sleeping thread wakes tens of µs late (about 50 µs on a VM),
    so that a write that must be at its time (a slave's response) is"""


class XferRunner(Protocol):
    """An xfer step (`pyrtu.drivers.xfer_runners.xfer_runner`: one per port): ``run(plan)``
    carries out one `XferPlan` (ValueError for values out of range)."""

    def run(self, plan: XferPlan) -> XferResult: ...


class AsyncXferRunner(Protocol):
    """Xfers on a thread of their own, for an event loop (one per port:
    `pyrtu.drivers.xfer_runners.async_xfer_runner`; C: csrc/rtu_xfer_io.c's worker,
    without the GIL).
    ``submit(plan)`` returns at once (RuntimeError while an xfer is under way);
    the loop watches ``fd`` (readable once it is over) and calls `result` (the last
    xfer's report; None while one is under way); `cancel` ends the xfer under
    way (before its write if that is not due yet: the report still comes, status
    CANCELLED); `close` ends the thread, the xfer under way cancelled."""

    fd: int

    def submit(self, plan: XferPlan) -> None: ...

    def result(self) -> XferResult | None: ...

    def cancel(self) -> None: ...

    def close(self) -> None: ...


#: how a Modbus TCP xfer ended (`TcpXferRunner.call`; csrc/rtu_tcp.h RTU_TCP_*)
(TCP_ANSWER, TCP_EXCEPTION, TCP_MISMATCH, TCP_TIMEOUT, TCP_CLOSED, TCP_ERRNO,
 TCP_BAD_HEADER, TCP_INTERRUPTED) = range(8)  # fmt: skip
#: `TcpXferRunner.call`'s word: the status is ``word & TCP_STATUS``; | this: late
#: answers were dropped, or an invalid header follows the answer (`TcpXferReport` has
#: them); ``word >> 8``: the answer's PDU length (``runner.answer[:word >> 8]``)
TCP_NOTE = 16
TCP_STATUS = 15
#: where a TCP_ERRNO xfer failed (`TcpXferReport.stage`)
STAGE_SEND, STAGE_RECEIVE = 1, 2
#: the receive buffer of a TCP xfer (late answers are kept for the log until it is
#: full; at least RTU_TCP_MIN_CAP)
TCP_CAPACITY = 8192


class TcpScan(NamedTuple):
    """What the scan of a TCP client's receive buffer found (csrc/rtu_tcp.h
    rtu_tcp_scan_result): ``data[:used]`` are whole ADUs: the answer at
    ``data[ans_off:ans_off + ans_len]`` (``ans_len`` 0: none) and ``late`` others
    (``late_after`` of them after the answer); ``error`` is the `MBAP_ERROR_BY_CODE`
    index of an invalid header at ``used`` (0: none)."""

    used: int = 0
    ans_off: int = 0
    ans_len: int = 0
    late: int = 0
    late_after: int = 0
    error: int = 0


class TcpXferReport(NamedTuple):
    """Everything a TCP xfer saw (`TcpXferRunner.report`)."""

    status: int
    """TCP_ANSWER (a response; a broadcast: the request went), TCP_EXCEPTION (an
    exception response), TCP_MISMATCH (the answer names another unit or function),
    TCP_TIMEOUT, TCP_CLOSED (the server closed the connection), TCP_ERRNO (``err``
    at ``stage``), TCP_BAD_HEADER (an invalid MBAP header: ``scan.error``),
    TCP_INTERRUPTED (a signal, C only: `TcpXferRunner.resume`)"""
    start: float
    """when the send began"""
    end: float
    """when the read that completed the answer returned"""
    data: bytes
    """what the receive buffer holds: late ADUs, the answer, the rest"""
    scan: TcpScan
    err: int
    """the errno of TCP_ERRNO"""
    stage: int
    """STAGE_SEND or STAGE_RECEIVE of TCP_ERRNO"""
    why: str = ""
    """the layer's own words for ``err`` where it has them (mbaps://'s TLS in C:
    OpenSSL's reason for an EPROTO, "decryption failed or bad record mac"); empty:
    the system's (os.strerror)"""


class TcpXferRunner(Protocol):
    """A Modbus TCP client's transactions on one connected socket, one per call
    (C: csrc/rtu_tcp_io.c through pyrtu/drivers/_cxfer.py, the GIL released; the
    twin: pyrtu/drivers/_pyxfer.py): build the MBAP request, send it, wait until
    ``timeout`` seconds after the send began for the answer of transaction ``tid``,
    read it whole by its length field (late answers of other transactions
    dropped), and judge its unit and function; ``call`` and ``resume`` return the
    word described at `TCP_NOTE`.  The receive buffer is kept from
    call to call: a partial answer read before a timeout is completed (and
    dropped as late) in the next call."""

    answer: Any
    """the answer's PDU after a call that found one: ``answer[:word >> 8]`` (bytes)"""

    def call(self, tid: int, unit: int, pdu: bytes, awaited: bool, timeout: float) -> int: ...

    def resume(self) -> int: ...

    def end(self) -> float: ...

    def report(self) -> TcpXferReport: ...


class TcpScanner(Protocol):
    """The scan of an event loop's Modbus TCP client (C: rtu_tcp_scan of
    csrc/rtu_tcp.c through pyrtu/drivers/_cxfer.py; the twin: `tcp_scan` of
    pyrtu/drivers/_pyxfer.py) over a receive buffer of its own, ``buf`` (the
    connection reads into it; it is never resized)."""

    buf: bytearray

    def scan(self, n: int, tid: int) -> TcpScan:
        """``buf[:n]`` scanned from 0 for the answer to ``tid`` (C: the
        rtu_tcp_scan_result itself, whose fields are `TcpScan`'s)."""
        ...


def check_plan(plan: XferPlan) -> None:
    """The values both backends refuse, with the same messages."""
    ex = plan.xfer
    if not ex.data:
        raise ValueError("request must not be empty")
    if not 0 <= ex.expect <= CAPACITY:
        raise ValueError(f"expect must be 0..{CAPACITY}, not {ex.expect}")
    if not 0 <= ex.short_len <= ex.expect:
        raise ValueError(f"short_len must be 0..expect ({ex.expect}), not {ex.short_len}")
    if not plan.char > 0:
        raise ValueError(f"char must be a positive number of seconds, not {plan.char}")
    if not ex.first_wake >= 0 or not ex.timeout >= 0:
        raise ValueError("first_wake and timeout must be non-negative numbers of seconds")
    if not 0 <= plan.spin <= SPIN_MAX:
        raise ValueError(f"spin must be 0..{SPIN_MAX} seconds, not {plan.spin}")
    if plan.fd < 0:
        raise ValueError(f"fd must be an open descriptor, not {plan.fd}")


__all__ = [
    "ANSWER",
    "CANCELLED",
    "CAPACITY",
    "ERRNO",
    "GONE",
    "SHORT",
    "SPIN_MAX",
    "STAGE_READ",
    "STAGE_RECEIVE",
    "STAGE_SEND",
    "STAGE_WRITE",
    "STALE",
    "TCP_ANSWER",
    "TCP_BAD_HEADER",
    "TCP_CAPACITY",
    "TCP_CLOSED",
    "TCP_ERRNO",
    "TCP_EXCEPTION",
    "TCP_INTERRUPTED",
    "TCP_MISMATCH",
    "TCP_NOTE",
    "TCP_STATUS",
    "TCP_TIMEOUT",
    "AsyncXferRunner",
    "TcpScan",
    "TcpXferReport",
    "TcpXferRunner",
    "XferPlan",
    "XferResult",
    "XferRunner",
    "check_plan",
]
