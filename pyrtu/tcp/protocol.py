"""The sans-I/O Modbus TCP client: requests out, answers matched by transaction id.

Messaging on TCP/IP Implementation Guide V1.0b, 3.1.3: the client picks the
transaction id; the server copies it, the protocol id and the unit id into its
answer, so several requests may be in flight on one connection and answers may
come back in any order.  No clock, no socket: time is an input::

    proto = TcpClientProtocol(timeout=1.0)
    tid, data = proto.send_request(unit, pdu, now)   # write ``data``
    proto.receive_data(chunk, now)                    # bytes read from the socket
    proto.handle_timer(now)                           # when now >= proto.deadline()
    while (done := proto.next_result()) is not None:
        tid, answer = done      # the response PDU, None (broadcast), or a ModbusError

Unit 0 is a broadcast (through a gateway): nothing comes back, the result is None
at once; unless ``answered=True``: a TCP device addressed with unit 0 directly
answers it (Messaging on TCP/IP Implementation Guide 4.4.1.2).  An answer for no
request in flight (a late one, after its timeout) is dropped and counted.  A header
the framer cannot accept ends the connection: every request in flight fails with
`FrameError` and ``broken`` is set.

At DEBUG level (``pyrtu -vv``) the ``pyrtu.drivers.master`` logger gets every frame
sent and received, whole (MBAP header and PDU), as a serial master logs its ADUs.

The blocking client (`pyrtu.tcp.client.TcpClient`, one request at a time) runs each
transaction's I/O in one call of a `pyrtu.drivers.xfer.TcpXferRunner` (C:
csrc/rtu_tcp_io.c, the GIL released) between `begin` and `answered` / `settle`
here: the same counters, log lines, errors and ``broken`` as the event path above.
"""

from __future__ import annotations

import logging
import os
from collections import deque
from collections.abc import Callable, Sequence

from pyrtu.core import _backend
from pyrtu.core._types import BytesLike
from pyrtu.core.frames import FrameKind
from pyrtu.core.mbap import (
    MAX_PDU,
    MBAP_ERROR_BY_CODE,
    MBAP_HEADER,
    MbapFrame,
    check_header_args,
)
from pyrtu.core.timing import positive_seconds
from pyrtu.drivers import xfer
from pyrtu.drivers.xfer import TcpXferRunner
from pyrtu.pdu.errors import (
    ExceptionResponseError,
    FrameError,
    ModbusError,
    NoResponseError,
    PortError,
)

Result = tuple[int, bytes | ModbusError | None]

#: the logger of the masters' frames (as `pyrtu.protocol.client`'s on a serial line)
log = logging.getLogger("pyrtu.drivers.master")


#: a request in flight: (unit, function, deadline, raw, sent): ``raw``: an exception
#: response is the result, as its PDU; ``sent``: when it was sent (for the log).  A
#: plain tuple: one is made per transaction, without a Python ``__init__``.
_Pending = tuple[int, int, float, bool, float]
_DEADLINE = 2  # (its index)


def check_timeout(timeout: object, name: str = "timeout") -> float:
    return positive_seconds(timeout, name)


def _mismatch(unit: int, fc: int, got_unit: int, got_fc: int) -> FrameError:
    return FrameError(
        f"answer to unit {unit} function {fc} came back as unit {got_unit} function {got_fc}",
        unit,
        fc,
    )


def _short_exception(size: int, unit: int, fc: int) -> FrameError:
    return FrameError(f"exception response of {size} bytes", unit, fc)


def _no_answer(unit: int, fc: int, timeout: float) -> NoResponseError:
    return NoResponseError(
        f"no answer from unit {unit} (function {fc}) within {timeout} s", unit, fc
    )


def _bad_header(error: object) -> FrameError:
    return FrameError(f"bad MBAP header from the server ({error})")


def _log_late(tid: int, adu: BytesLike) -> None:
    log.debug("RX late (no request tid %d in flight), dropped: %s", tid, bytes(adu).hex(" "))


class TcpClientProtocol:
    """One Modbus TCP connection seen from the client (see the module docstring)."""

    def __init__(
        self, *, timeout: float = 1.0, max_in_flight: int = 16, where: str = "tcp"
    ) -> None:
        self.where = where
        self.timeout = check_timeout(timeout)
        if isinstance(max_in_flight, bool) or not isinstance(max_in_flight, int):
            raise TypeError(f"max_in_flight must be an integer, not {max_in_flight!r}")
        if not 1 <= max_in_flight <= 65535:
            raise ValueError(f"max_in_flight must be 1..65535, not {max_in_flight}")
        self.max_in_flight = max_in_flight
        self._framer = _backend.active.MbapFramer("master")
        self._pending: dict[int, _Pending] = {}
        self._results: deque[Result] = deque()
        self._tid = 0
        self.broken: ModbusError | None = None
        #: when the latest answer to a request in flight arrived (the ``now`` of its
        #: `receive_data`), None before the first
        self.answer_end: float | None = None
        self.counters = dict.fromkeys(
            # the names of `pyrtu.Master.counters` where they mean the same
            (
                "requests",
                "responses",
                "broadcasts",
                "exceptions",
                "timeouts",
                "frame_errors",
                "late",
            ),
            0,
        )

    @property
    def in_flight(self) -> int:
        return len(self._pending)

    def _next_tid(self) -> int:
        for _ in range(65536):
            self._tid = (self._tid + 1) & 0xFFFF
            if self._tid not in self._pending:
                return self._tid
        raise RuntimeError("no free transaction id")  # unreachable: max_in_flight < 65536

    def _request_body(self, unit: int, pdu: BytesLike) -> bytes:
        """``pdu`` as bytes for ``unit``; ValueError/TypeError for bad arguments,
        PortError when the connection is broken, before anything is sent."""
        if (
            type(pdu) is bytes
            and 0 < len(pdu) <= MAX_PDU
            and type(unit) is int
            and 0 <= unit <= 255
        ):
            body = pdu  # (what the masters' request table builds: checked already)
        else:
            body = check_header_args(0, unit, pdu)
        if self.broken is not None:
            raise PortError(self.where, f"the connection is unusable: {self.broken}")
        return body

    def send_request(
        self,
        unit: int,
        pdu: BytesLike,
        now: float,
        *,
        answered: bool | None = None,
        raw: bool = False,
    ) -> tuple[int, bytes]:
        """A new transaction: its id and the bytes to write.  ``answered``: whether an
        answer is awaited (None: for every unit but 0, the broadcast); ``raw``: an
        exception response is the result (its PDU), not `ExceptionResponseError`.
        Raises before anything is sent: ValueError/TypeError for bad arguments,
        RuntimeError when ``max_in_flight`` requests already wait or the connection
        is broken."""
        if (
            type(pdu) is bytes
            and 0 < len(pdu) <= MAX_PDU
            and type(unit) is int
            and 0 <= unit <= 255
            and self.broken is None
        ):
            body = pdu  # (`_request_body`'s common case, without its call)
        else:
            body = self._request_body(unit, pdu)
        pending = self._pending
        if len(pending) >= self.max_in_flight:
            raise RuntimeError(f"{self.max_in_flight} requests already in flight")
        tid = (self._tid + 1) & 0xFFFF
        if tid in pending:  # (wrapped around to one still in flight: the next free)
            tid = self._next_tid()
        self._tid = tid
        data = MBAP_HEADER.pack(tid, 0, len(body) + 1, unit) + body  # (3.1.3: the MBAP ADU)
        counters = self.counters
        counters["requests"] += 1
        if unit == 0 if answered is None else not answered:  # a broadcast
            counters["broadcasts"] += 1
            self._results.append((tid, None))
        else:
            pending[tid] = (unit, body[0], now + self.timeout, raw, now)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("TX unit %d fc %d tid %d: %s", unit, body[0], tid, data.hex(" "))
        return tid, data

    def receive_data(self, data: BytesLike, now: float) -> None:
        """Bytes read from the connection (``b""``: the server closed it)."""
        if self.broken is not None:
            return
        self._framer.receive_data(data)
        while (ev := self._framer.next_event()) is not None:
            if ev.error is not None:
                if ev.error.value == "truncated":
                    continue  # the close below fails what is in flight
                self._fail_all(_bad_header(ev.error))
                return
            self._answer(ev.transaction, ev.unit, ev.kind, ev.pdu, now)
        if not data:
            self.connection_lost("the server closed the connection")

    def _answer(self, tid: int, unit: int, kind: FrameKind, pdu: bytes, now: float) -> None:
        # (kind: FrameKind.EXCEPTION exactly when the function code has bit 7 set)
        result = self.take_answer(tid, unit, pdu, now)
        if result is not None:
            self._results.append((tid, result))

    def take_answer(
        self, tid: int, unit: int, pdu: bytes, now: float
    ) -> bytes | ModbusError | None:
        """The result of an answer read at ``now`` (counted and logged, as
        `receive_data` does): the response PDU, an exception response's PDU
        (``raw``) or the error; None for a late one (no request ``tid`` in flight:
        dropped).  The event loop's client calls it for the one answer a read
        brought (`sole_tid`), and resolves the awaiting future itself."""
        pending = self._pending.pop(tid, None)
        counters = self.counters
        if pending is None:
            if log.isEnabledFor(logging.DEBUG):
                _log_late(tid, MBAP_HEADER.pack(tid, 0, len(pdu) + 1, unit) + pdu)
            counters["late"] += 1
            return None
        asked, fc, _, raw, sent = pending
        if log.isEnabledFor(logging.DEBUG):
            self._log_answer(tid, unit, pdu, (now - sent) * 1e3)
        self.answer_end = now
        if unit != asked or pdu[0] & 0x7F != fc:
            counters["frame_errors"] += 1
            return _mismatch(asked, fc, unit, pdu[0])
        if pdu[0] & 0x80:  # an exception response
            counters["exceptions"] += 1
            if len(pdu) != 2:
                counters["frame_errors"] += 1
                return _short_exception(len(pdu), unit, fc)
            if raw:
                return pdu
            return ExceptionResponseError(unit, fc, pdu[1])
        counters["responses"] += 1
        return pdu

    def receive_datagram(
        self, data: BytesLike, now: float, parse: Callable[[bytes, str], Sequence[MbapFrame]]
    ) -> bool:
        """One datagram read (Modbus over UDP, `pyrtu.tcp.udp`: one whole ADU per
        datagram, framed by ``parse``: a backend's ``parse_tcp_stream``, C or the
        twin): an answer as `receive_data` takes it.  Anything but exactly one
        valid ADU (a bad header, a length field that does not end the datagram) is
        dropped and counted (``frame_errors``): False.  Nothing is broken by it, as
        there is no stream to lose."""
        raw = bytes(data)
        frames = parse(raw, "master")
        frame = frames[0] if len(frames) == 1 else None
        if frame is None or frame.error is not None or len(frame.adu) != len(raw):
            self.counters["frame_errors"] += 1
            log.debug("RX datagram not one whole ADU, dropped: %s", raw.hex(" "))
            return False
        result = self.take_answer(frame.transaction, frame.unit, frame.pdu, now)
        if result is not None:
            self._results.append((frame.transaction, result))
        return True

    def sole_tid(self) -> int:
        """The transaction id of the one request in flight, or -1 (none, or several)."""
        pending = self._pending
        return next(iter(pending)) if len(pending) == 1 else -1

    def receive_scanned(self, data: bytes, used: int, error: int, now: float) -> None:
        """What a scan of the bytes read found (`pyrtu.drivers.xfer.TcpScanner`):
        ``data[:used]`` whole ADUs, each an answer as `receive_data` takes them (in
        order); ``error``: an invalid header after them (`MBAP_ERROR_BY_CODE`'s
        index, 0: none), which ends the connection."""
        if self.broken is not None:
            return
        for adu in _adus(data, 0, used):
            tid = adu[0] << 8 | adu[1]
            result = self.take_answer(tid, adu[6], adu[7:], now)
            if result is not None:
                self._results.append((tid, result))
        if error:
            self._fail_all(_bad_header(MBAP_ERROR_BY_CODE[error]))

    def _fail_all(self, error: ModbusError) -> None:
        self.broken = error
        for tid in sorted(self._pending):
            self._results.append((tid, error))
        self._pending.clear()

    def connection_lost(self, reason: str) -> None:
        """The connection ended: every request in flight fails with `PortError`."""
        if self.broken is None:
            self._fail_all(PortError(self.where, reason))

    def reset(self) -> None:
        """A new connection in place of the old one (a reconnect): nothing in flight,
        nothing broken, nothing half read; the counters and the transaction ids go
        on.  What was in flight failed when the old connection ended."""
        self._framer = _backend.active.MbapFramer("master")
        self._pending.clear()
        self._results.clear()
        self.broken = None

    def refused(self, reason: str) -> None:
        """No answer will come to what is in flight (Modbus over UDP: the host said
        ICMP port unreachable): each request fails with `NoResponseError` naming
        ``reason`` (counted as ``timeouts``: no answer came, as when its deadline
        passes); nothing is broken (a retry may be answered)."""
        for tid in sorted(self._pending):
            unit, fc, *_ = self._pending.pop(tid)
            self.counters["timeouts"] += 1
            text = f"no answer from unit {unit} (function {fc}): {reason}"
            self._results.append((tid, NoResponseError(text, unit, fc)))

    def deadline(self) -> float | None:
        """When the oldest request in flight times out, or None."""
        if not self._pending:
            return None
        return min(p[_DEADLINE] for p in self._pending.values())

    def handle_timer(self, now: float) -> None:
        expired = [tid for tid, p in self._pending.items() if p[_DEADLINE] <= now]
        for tid in expired:
            unit, fc, *_ = self._pending.pop(tid)
            self.counters["timeouts"] += 1
            self._results.append((tid, _no_answer(unit, fc, self.timeout)))

    def cancel(self, tid: int) -> None:
        """Forget a request (its caller gave up): a late answer is dropped."""
        self._pending.pop(tid, None)

    def has_results(self) -> bool:
        """Whether `next_result` has one."""
        return bool(self._results)

    def next_result(self) -> Result | None:
        return self._results.popleft() if self._results else None

    # ------------------------------------------ the blocking client's transactions

    def begin(self, unit: int, pdu: BytesLike, answered: bool | None) -> tuple[int, bytes, bool]:
        """A blocking client's new transaction (nothing else in flight): its
        transaction id, the PDU as bytes and whether an answer is awaited; counted
        and logged as `send_request` does, with the same errors before anything is
        sent.  Its I/O is one `TcpXferRunner.call`; then `answered` or `settle`."""
        body = self._request_body(unit, pdu)
        tid = self._tid = (self._tid + 1) & 0xFFFF
        counters = self.counters
        counters["requests"] += 1
        awaited = unit != 0 if answered is None else bool(answered)
        if not awaited:
            counters["broadcasts"] += 1
        if log.isEnabledFor(logging.DEBUG):
            data = MBAP_HEADER.pack(tid, 0, len(body) + 1, unit) + body
            log.debug("TX unit %d fc %d tid %d: %s", unit, body[0], tid, data.hex(" "))
        return tid, body, awaited

    def repeated(self, tid: int) -> None:
        """A transaction the mux sent again on its own (`pyrtu.tcp.mux.TcpMux.repeat`)
        as ``tid``: counted as `begin` counts one, and the next id follows it."""
        self._tid = tid
        self.counters["requests"] += 1

    def answered(self, tid: int, unit: int, pdu: bytes, runner: TcpXferRunner) -> float:
        """The response ``pdu`` the runner's call ended with (TCP_ANSWER, nothing
        late, awaited): counted, logged; when it came."""
        self.answer_end = end = runner.end()
        self.counters["responses"] += 1
        if log.isEnabledFor(logging.DEBUG):
            self._log_answer(tid, unit, pdu, (end - runner.report().start) * 1e3)
        return end

    @staticmethod
    def _log_answer(tid: int, unit: int, pdu: bytes, ms: float) -> None:
        adu = (MBAP_HEADER.pack(tid, 0, len(pdu) + 1, unit) + pdu).hex(" ")
        log.debug("RX unit %d fc %d tid %d: %s (%.3f ms)", unit, pdu[0], tid, adu, ms)

    def settle(
        self, tid: int, unit: int, fc: int, raw: bool, runner: TcpXferRunner
    ) -> bytes | None:
        """The result of the runner's call however it ended (`answered` is the
        common case's shortcut): the response PDU, None (a broadcast), an exception
        response's PDU (``raw``), or the error raised, as the event path gives them."""
        r = runner.report()
        scan, data = r.scan, r.data
        status = r.status
        self.counters["late"] += scan.late
        if scan.late and log.isEnabledFor(logging.DEBUG):
            first = scan.ans_off if scan.ans_len else scan.used
            for adu in _adus(data, 0, first):
                _log_late(adu[0] << 8 | adu[1], adu)
        if status in (xfer.TCP_ANSWER, xfer.TCP_EXCEPTION, xfer.TCP_MISMATCH) and scan.ans_len:
            try:
                return self._judge(tid, unit, fc, raw, r)
            finally:
                if scan.late_after and log.isEnabledFor(logging.DEBUG):
                    for adu in _adus(data, scan.ans_off + scan.ans_len, scan.used):
                        _log_late(adu[0] << 8 | adu[1], adu)
                if scan.error:  # after the answer: the stream is lost from here
                    self.broken = _bad_header(MBAP_ERROR_BY_CODE[scan.error])
        if status == xfer.TCP_ANSWER:
            return None  # a broadcast went out
        if status == xfer.TCP_TIMEOUT:
            self.counters["timeouts"] += 1
            raise _no_answer(unit, fc, self.timeout)
        if status == xfer.TCP_BAD_HEADER:
            self._fail_all(_bad_header(MBAP_ERROR_BY_CODE[scan.error]))
        elif status == xfer.TCP_CLOSED:
            self.connection_lost("the server closed the connection")
        elif status == xfer.TCP_ERRNO:
            what = "send" if r.stage == xfer.STAGE_SEND else "receive"
            self.connection_lost(f"{what} failed: {OSError(r.err, r.why or os.strerror(r.err))}")
        else:
            raise RuntimeError(f"TCP xfer status {status}")  # (INTERRUPTED: resumed first)
        assert self.broken is not None
        raise self.broken

    def _judge(self, tid: int, unit: int, fc: int, raw: bool, r: xfer.TcpXferReport) -> bytes:
        scan = r.scan
        adu = r.data[scan.ans_off : scan.ans_off + scan.ans_len]
        got_unit, pdu = adu[6], adu[7:]
        self.answer_end = r.end
        if log.isEnabledFor(logging.DEBUG):
            self._log_answer(tid, got_unit, pdu, (r.end - r.start) * 1e3)
        counters = self.counters
        if r.status == xfer.TCP_MISMATCH:
            counters["frame_errors"] += 1
            raise _mismatch(unit, fc, got_unit, pdu[0])
        if r.status == xfer.TCP_EXCEPTION:
            counters["exceptions"] += 1
            if len(pdu) != 2:
                counters["frame_errors"] += 1
                raise _short_exception(len(pdu), unit, fc)
            if raw:
                return pdu
            raise ExceptionResponseError(unit, fc, pdu[1])
        counters["responses"] += 1
        return pdu


def _adus(data: bytes, start: int, stop: int) -> list[bytes]:
    """The whole ADUs of ``data[start:stop]`` (a run of them, as a scan found)."""
    out = []
    while start < stop:
        end = start + 6 + (data[start + 4] << 8 | data[start + 5])
        out.append(data[start:end])
        start = end
    return out
