"""A check of the user's own line: one device, read over and over, timed at every step
the operating system lets a program see.

For a serial port the check sends the request itself (the bytes of FC 03, or FC 04,
built by `pyrtu.pdu` and checked by the framer), so that it sees:

- ``start``: the request handed to the port; ``sent``: the port says the last bit is
  out (``tcdrain``: pyserial's ``flush``);
- ``first``/``last``: when the answer's first and last bytes were read, and in how
  many reads (``chunks``) they came.

From the line's format it knows each frame's time on the wire (Serial Line 2.5.1:
11 bits a character with a parity bit or two stop bits, 10 without) and so derives:

- the **round trip** (``last - start``), its median, p99 and maximum;
- the **sending lag** of the port and adapter: ``sent - start`` less the request's wire
  time (a USB adapter reports "sent" when the bytes are in its buffer, so this can be
  negative: then they left the computer before reaching the wire, which the
  operating system cannot see);
- the **answer's start** after the request (``first - sent``): the device's turnaround
  plus the adapter's receive latency (a program cannot tell the two apart without a
  second port listening on the line; on the virtual bus the adapter adds nothing);
- the **adapter's batching**: an answer of ``n`` characters takes ``n`` character times
  on the wire; read through an adapter that forwards each byte at once its reads span
  about that; an adapter that holds bytes (an FTDI latency timer, a USB packet) hands
  them over in one read, ``batching`` = the wire time of the answer less the time its
  reads spanned is the least it added;
- what pyrtu **recommends**: a timeout (the largest round trip seen, times 1.5, and at
  least twice the p99, rounded up to 10 ms) and the inter-frame setting (with a
  batching adapter the silences between frames cannot be observed: pyrtu's default
  lenient framing ends frames by their predicted length and CRC, and ``strict=True``
  would discard good frames; else the t3.5 of the spec at this speed).

For ``tcp://`` and ``rtu+tcp://`` URLs there is no wire time to subtract: the check
times the transactions of a `pyrtu.Master` and recommends a timeout."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from pyrtu.bench.timer import percentile

TABLES = {"holding": 3, "input": 4}


@dataclass(frozen=True)
class Sample:
    start: float
    sent: float
    first: float
    last: float
    chunks: int


@dataclass
class LineReport:
    port: str
    slave: int
    table: str
    address: int
    count: int
    baudrate: int | None
    char: float | None  # seconds a character on the wire (None: TCP)
    request_wire: float | None
    answer_wire: float | None
    samples: list[Sample] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    round_trips: list[float] = field(default_factory=list)

    # -- the figures ---------------------------------------------------------------------
    def figures(self) -> dict[str, Any]:
        rt = self.round_trips
        out: dict[str, Any] = {
            "port": self.port,
            "slave": self.slave,
            "table": self.table,
            "address": self.address,
            "count": self.count,
            "transactions": len(rt),
            "failures": len(self.failures),
        }
        if not rt:
            return out
        out.update(
            round_trip_p50=percentile(rt, 0.5),
            round_trip_p99=percentile(rt, 0.99),
            round_trip_max=max(rt),
        )
        if self.samples and self.char is not None:
            assert self.request_wire is not None and self.answer_wire is not None
            s = self.samples
            lag = [x.sent - x.start - self.request_wire for x in s]
            answer_start = [x.first - x.sent for x in s]
            spans = [x.last - x.first for x in s]
            batching = [max(0.0, self.answer_wire - self.char - span) for span in spans]
            out.update(
                baudrate=self.baudrate,
                char=self.char,
                request_wire=self.request_wire,
                answer_wire=self.answer_wire,
                sending_lag_p50=percentile(lag, 0.5),
                answer_start_p50=percentile(answer_start, 0.5),
                answer_start_min=min(answer_start),
                reads_per_answer_p50=percentile([float(x.chunks) for x in s], 0.5),
                batching_p50=percentile(batching, 0.5),
                batches=self.batches(),
            )
        out.update(self.recommend())
        return out

    def batches(self) -> bool:
        """Whether the adapter hands over answers in lumps: most answers of more than
        four characters come in one read whose span is under half their wire time."""
        if self.char is None or self.answer_wire is None or self.answer_wire < 4 * self.char:
            return False
        lumped = [
            x for x in self.samples if x.chunks == 1 or x.last - x.first < self.answer_wire / 2
        ]
        return len(lumped) * 2 > len(self.samples)

    def recommend(self) -> dict[str, Any]:
        rt = self.round_trips
        timeout = max(1.5 * max(rt), 2 * percentile(rt, 0.99))
        timeout = math.ceil(timeout * 100 - 1e-9) / 100  # up to the next 10 ms
        out: dict[str, Any] = {"recommended_timeout": timeout}
        if self.char is None:
            return out
        if self.batches():
            out["recommended_framing"] = (
                "lenient (pyrtu's default): the adapter hands over bytes in lumps, so the "
                "silences between frames cannot be seen; do not use strict=True"
            )
        else:
            assert self.baudrate is not None
            t35 = 3.5 * self.char if self.baudrate <= 19200 else 0.00175
            out["recommended_framing"] = (
                f"the spec's t3.5 ({t35 * 1e3:.3f} ms at {self.baudrate} baud) is observable "
                "here: strict=True may be used"
            )
        return out


def char_time(baudrate: int, parity: str, stopbits: float, bytesize: int) -> float:
    """Seconds a character takes on the wire: start, data, parity, stop bits."""
    bits = 1 + bytesize + (parity != "N") + stopbits
    return bits / baudrate


def check_serial(
    port: str,
    slave: int,
    *,
    baudrate: int,
    parity: str,
    stopbits: float,
    bytesize: int,
    table: str = "holding",
    address: int = 0,
    count: int = 1,
    samples: int = 100,
    timeout: float = 1.0,
    exclusive: bool = True,
) -> LineReport:
    """Read ``count`` registers of ``table`` at ``address`` from ``slave``, ``samples``
    times, on a serial port (see the module's text)."""
    from pyrtu.drivers.port import open_port

    if table not in TABLES:
        raise ValueError(f"table must be one of {sorted(TABLES)}, not {table!r}")
    char = char_time(baudrate, parity, stopbits, bytesize)
    request = _request(slave, TABLES[table], address, count)
    answer_size = 5 + 2 * count
    report = LineReport(
        port, slave, table, address, count, baudrate, char, len(request) * char, answer_size * char
    )
    p = open_port(
        port,
        baudrate=baudrate,
        parity=parity,
        stopbits=stopbits,
        bytesize=bytesize,
        exclusive=exclusive,
    )
    try:
        gap = 3.5 * char if baudrate <= 19200 else 0.00175  # t3.5 (Serial Line 2.5.1.1)
        for _ in range(samples):
            sample, why = _one(p, request, answer_size, timeout)
            if sample is None:
                report.failures.append(why)
                _drain(p, gap + timeout / 10)  # a late answer must not meet the next request
            else:
                report.samples.append(sample)
                report.round_trips.append(sample.last - sample.start)
            time.sleep(gap)
    finally:
        p.close()
    return report


def _request(slave: int, function: int, address: int, count: int) -> bytes:
    from pyrtu.core._backend import active

    return bytes(
        active.add_crc(
            bytes([slave, function]) + address.to_bytes(2, "big") + count.to_bytes(2, "big")
        )
    )


def _one(p: Any, request: bytes, answer_size: int, timeout: float) -> tuple[Sample | None, str]:
    """One transaction: (its sample, "") or (None, what went wrong)."""
    import os

    from pyrtu.core._backend import active

    start = time.monotonic()
    if p.fd is not None:
        os.write(p.fd, request)
        if p.has_wire:
            import termios

            termios.tcdrain(p.fd)
    else:
        p.serial.write(request)
        p.serial.flush()
    sent = time.monotonic()
    data = b""
    first = last = 0.0
    chunks = 0
    deadline = sent + timeout
    need = answer_size
    while len(data) < need:
        left = deadline - time.monotonic()
        if left <= 0:
            return None, f"no complete answer within {timeout:g} s ({len(data)} bytes)"
        got = p.read(left)
        if not got:
            continue
        now = time.monotonic()
        if not data:
            first = now
        data += got
        last = now
        chunks += 1
        if len(data) >= 2 and data[1] & 0x80:
            need = 5  # an exception answer
    if data[0] != request[0] or (data[1] & 0x7F) != request[1]:
        return None, f"an answer from another slave or function: {data.hex(' ')}"
    if not active.check_crc(data[:need]):
        return None, f"a bad CRC: {data.hex(' ')}"
    if data[1] & 0x80:
        return None, f"exception {data[2]} (check --slave, --table, --address)"
    return Sample(start, sent, first, last, chunks), ""


def _drain(p: Any, quiet: float) -> None:
    """Read and drop what comes until ``quiet`` seconds pass without a byte."""
    while p.read(quiet):
        continue


def check_tcp(
    url: str,
    slave: int,
    *,
    table: str = "holding",
    address: int = 0,
    count: int = 1,
    samples: int = 100,
    timeout: float = 1.0,
) -> LineReport:
    """The same over a ``tcp://`` or ``rtu+tcp://`` URL, through `pyrtu.Master`: round
    trips and the recommended timeout (there is no wire time to subtract)."""
    from pyrtu.drivers.master import Master
    from pyrtu.pdu.errors import ModbusError

    if table not in TABLES:
        raise ValueError(f"table must be one of {sorted(TABLES)}, not {table!r}")
    report = LineReport(url, slave, table, address, count, None, None, None, None)
    read_name = "read_holding_registers" if table == "holding" else "read_input_registers"
    with Master(url, timeout=timeout) as m:
        read = getattr(m, read_name)
        for _ in range(samples):
            t0 = time.monotonic()
            try:
                read(slave, address, count)
            except ModbusError as exc:
                report.failures.append(str(exc))
                continue
            report.round_trips.append(time.monotonic() - t0)
    return report


__all__ = ["TABLES", "LineReport", "Sample", "char_time", "check_serial", "check_tcp"]
