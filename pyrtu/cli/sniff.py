"""``pyrtu sniff``: decode the traffic of a bus with the monitor framer.

Live, from a port that hears the bus (an RS-485 adapter that only listens, a drop
of the virtual bus), or from a capture file (``--capture FILE``, the format of
``pyrtu vbus --capture``; its header gives the baud rate and format), or from a
small built-in sample (``--example``: two slaves, an exception, a vendor code,
noise, and a frame a USB adapter delivered in two pieces).

The monitor framer tells requests from responses by their lengths and its
pending request; every frame is shown with its function and fields, and with
``--profile NAME`` (a device template: cfw100, cfw320, cfw701, cv100, act, acu or
any of ``pyrtu template list``, or a ``.toml`` file) in the device's terms:
``P680 status: running, forward, remote``.  The profile also gives the framer
the vendor's function codes (Bonfiglioli FC 100/101, CV100 0x41-0x43).

Stops at the end of a capture, after ``--count`` frames or ``--duration``, or on
SIGINT/SIGTERM.  ``--json``: one JSON line per frame (``"type": "frame"``), then
one summary line (``"type": "summary"``).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

from pyrtu.cli._subcommand import subcommand
from pyrtu.cli.common import (
    EXIT_OK,
    SignalStop,
    add_count_option,
    add_duration_option,
    add_json_option,
    add_serial_options,
    emit,
    framing_kwargs,
    serial_kwargs,
    stop_on_signals,
)
from pyrtu.cli.template import add_profile_option, register_notes

VENDOR_NAMES = {
    "bonfiglioli": {100: "read_parameter_32", 101: "write_parameter_32"},
    "cv100": {0x41: "write_register_save", 0x42: "manage", 0x43: "write_registers_save"},
}


def _vendor_of(profile: str | None) -> str | None:
    """The vendor function set (`VENDOR_NAMES`) of template ``profile`` (its ``rules``)."""
    if not profile:
        return None
    from pyrtu.devices.registry import find_template

    return find_template(profile).rules


@dataclass
class Seen:
    """A frame or discard event, for RTU and ASCII alike."""

    kind: str  # request, response, exception, unknown, discard
    message: bytes  # address + PDU (b"" for a discard)
    raw: bytes  # as on the wire
    start: float | None
    error: str | None = None

    @property
    def slave(self) -> int:
        return self.message[0] if self.message else -1

    @property
    def function(self) -> int:
        return self.message[1] if len(self.message) > 1 else -1


@dataclass
class Decoded:
    summary: str
    fields: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _u16(b: bytes, at: int) -> int:
    return int.from_bytes(b[at : at + 2], "big")


def _words(b: bytes) -> list[int]:
    return [_u16(b, i) for i in range(0, len(b) - 1, 2)]


class Decoder:
    """Fields of frames, pairing each response with the request it answers."""

    def __init__(self, profile: str | None = None, vendor: str | None = None) -> None:
        self.profile = profile
        vendor = vendor or _vendor_of(profile)
        self.vendor_names = VENDOR_NAMES.get(vendor or "", {})
        self.pending: dict[int, bytes] = {}  # slave -> the request PDU it has to answer

    def function_name(self, function: int) -> str:
        from pyrtu.pdu import FUNCTION_NAMES

        f = function & 0x7F
        return FUNCTION_NAMES.get(f) or self.vendor_names.get(f) or f"function 0x{f:02X}"

    def _notes(self, address: int, values: Iterable[int], table: str = "holding") -> list[str]:
        if not self.profile:
            return []
        return list(register_notes(self.profile, address, list(values), table).values())

    def decode(self, seen: Seen) -> Decoded:
        if seen.error is not None:
            return Decoded(f"{len(seen.raw)} bytes discarded ({seen.error}): {seen.raw.hex(' ')}")
        pdu = seen.message[1:]
        try:
            if seen.kind == "exception":
                self.pending.pop(seen.slave, None)
                from pyrtu.pdu.errors import exception_name

                code = pdu[1]
                return Decoded(
                    f"exception {code} ({exception_name(code)})", {"exception_code": code}
                )
            if seen.kind == "request":
                if seen.slave != 0:
                    self.pending[seen.slave] = pdu
                return self._request(pdu)
            if seen.kind == "response":
                request = self.pending.pop(seen.slave, b"")
                return self._response(pdu, request if request[:1] == pdu[:1] else b"")
        except IndexError:
            pass
        return Decoded(pdu[1:].hex(" "), {"data": pdu[1:].hex()})

    def _request(self, pdu: bytes) -> Decoded:
        f, d = pdu[0], pdu[1:]
        if f in (1, 2, 3, 4) and len(d) == 4:
            a, n = _u16(d, 0), _u16(d, 2)
            return Decoded(
                f"{a}..{a + n - 1} ({n})" if n > 1 else f"{a}", {"address": a, "count": n}
            )
        if f in (5, 6, 0x41) and len(d) == 4:
            return self._single(f, _u16(d, 0), _u16(d, 2))
        if f in (15, 16, 0x43) and len(d) >= 5:
            a, n = _u16(d, 0), _u16(d, 2)
            span = f"{a}..{a + n - 1}" if n > 1 else f"{a}"
            if f == 15:
                bits = [bool(d[5 + i // 8] >> (i % 8) & 1) for i in range(n) if 5 + i // 8 < len(d)]
                return Decoded(
                    f"{span} = {''.join('1' if b else '0' for b in bits)}",
                    {"address": a, "count": n, "values": bits},
                )
            values = _words(d[5:])
            return Decoded(
                f"{span} = {' '.join(str(v) for v in values)}",
                {"address": a, "count": n, "values": values},
                self._notes(a, values),
            )
        if f == 8 and len(d) == 4:
            sub, data = _u16(d, 0), _u16(d, 2)
            return Decoded(
                f"sub-function 0x{sub:02X} data 0x{data:04X}", {"sub_function": sub, "data": data}
            )
        if f == 43 and len(d) == 3:
            return Decoded(
                f"MEI 0x{d[0]:02X} read code {d[1]} object {d[2]}",
                {"mei": d[0], "read_code": d[1], "object": d[2]},
            )
        if f == 100 and self.vendor_names and len(d) == 2:
            return Decoded(f"parameter address {_u16(d, 0)}", {"address": _u16(d, 0)})
        if f == 101 and self.vendor_names and len(d) == 6:
            a, v = _u16(d, 0), int.from_bytes(d[2:6], "big")
            return Decoded(f"{a} = {v}", {"address": a, "value": v}, self._notes(a, [v]))
        return Decoded(d.hex(" "), {"data": d.hex()})

    def _single(self, f: int, a: int, v: int) -> Decoded:
        if f == 5:
            on = v == 0xFF00
            return Decoded(f"{a} = {'ON' if on else 'OFF'}", {"address": a, "value": on})
        return Decoded(f"{a} = {v} (0x{v:04X})", {"address": a, "value": v}, self._notes(a, [v]))

    def _response(self, pdu: bytes, request: bytes) -> Decoded:
        f, d = pdu[0], pdu[1:]
        req = request[1:]
        if f in (3, 4) and d and len(d) == 1 + d[0]:
            values = _words(d[1:])
            if len(req) == 4:
                a = _u16(req, 0)
                shown = " ".join(f"[{a + i}] {v}" for i, v in enumerate(values))
                table = "holding" if f == 3 else "input"
                named = self._notes(a, values, table)
                return Decoded(shown, {"address": a, "values": values}, named)
            return Decoded(" ".join(str(v) for v in values), {"values": values})
        if f in (1, 2) and d and len(d) == 1 + d[0]:
            n = _u16(req, 2) if len(req) == 4 else 8 * d[0]
            bits = [bool(d[1 + i // 8] >> (i % 8) & 1) for i in range(n) if 1 + i // 8 < len(d)]
            fields: dict[str, Any] = {"values": bits}
            if len(req) == 4:
                fields["address"] = _u16(req, 0)
            return Decoded("".join("1" if b else "0" for b in bits), fields)
        if f in (5, 6, 0x41) and len(d) == 4:
            return self._single(f, _u16(d, 0), _u16(d, 2))
        if f in (15, 16, 0x43) and len(d) == 4:
            a, n = _u16(d, 0), _u16(d, 2)
            return Decoded(f"{a} ({n} written)", {"address": a, "count": n})
        if f == 43 and len(d) >= 6:
            return self._identification(d)
        if f == 100 and self.vendor_names and len(d) == 4:
            v = int.from_bytes(d, "big")
            fields = {"value": v}
            notes: list[str] = []
            if len(req) == 2:
                fields["address"] = _u16(req, 0)
                notes = self._notes(_u16(req, 0), [v])
            return Decoded(f"= {v}", fields, notes)
        if f == 101 and self.vendor_names and len(d) == 6:
            a, v = _u16(d, 0), int.from_bytes(d[2:6], "big")
            return Decoded(f"{a} = {v} (written)", {"address": a, "value": v})
        return Decoded(d.hex(" "), {"data": d.hex()})

    @staticmethod
    def _identification(d: bytes) -> Decoded:
        objects: dict[int, str] = {}
        at, count = 6, d[5]
        for _ in range(count):
            oid, n = d[at], d[at + 1]
            objects[oid] = d[at + 2 : at + 2 + n].decode("ascii", "replace")
            at += 2 + n
        return Decoded(
            " ".join(objects.values()), {"objects": {str(k): v for k, v in objects.items()}}
        )


# -- sources ----------------------------------------------------------------------------


def _rules(profile: str | None) -> dict[int, Any]:
    from pyrtu.core.rules import BONFIGLIOLI, CV100

    vendor = _vendor_of(profile)
    return dict(BONFIGLIOLI if vendor == "bonfiglioli" else CV100 if vendor == "cv100" else {})


def _seen_rtu(frame: Any) -> Seen:
    error = frame.error.value if frame.error is not None else None
    return Seen(
        "discard" if error else str(frame.kind),
        b"" if error else frame.adu[:-2],
        frame.adu,
        frame.start,
        error,
    )


def from_capture(reader: Any, profile: str | None, args: argparse.Namespace) -> Iterator[Seen]:
    """The frames of an open `CaptureReader`, streamed (memory bounded by a constant)."""
    from pyrtu.vbus.capture import capture_frames

    options: dict[str, Any] = {"timing": args.timing, "t35": args.t35}
    rules = _rules(profile)
    if rules:
        options["rules"] = rules
    for frame in capture_frames(reader, **options):
        yield _seen_rtu(frame)


def open_capture(path: str) -> Any:
    """A `CaptureReader` for ``--capture``; unreadable files raise `PortError` (exit 3)."""
    from pyrtu.pdu.errors import PortError
    from pyrtu.vbus.capture import CaptureError, CaptureReader

    try:
        return CaptureReader(path)
    except CaptureError as exc:
        raise PortError(path, str(exc).removeprefix(f"{path}: ")) from None
    except IsADirectoryError:
        raise PortError(path, "is a directory, not a capture file") from None


def capture_warnings(reader: Any) -> list[str]:
    """What a finished capture read has to say (a cut last record, merge trouble)."""
    out = []
    if reader.truncated is not None:
        out.append(f"{reader.path}: {reader.truncated}")
    if reader.late:
        out.append(
            f"{reader.path}: {reader.late} runs of bytes came after later ones beyond the"
            " reordering window (the file is damaged or not written by pyrtu)"
        )
    return out


def from_example(profile: str | None) -> Iterator[Seen]:
    from pyrtu.core._backend import active
    from pyrtu.core.rules import BONFIGLIOLI

    data, chunks = example_capture()
    rules = _rules(profile) or dict(BONFIGLIOLI)
    for frame in active.parse_stream(data, "monitor", chunks=chunks, rules=rules):
        yield _seen_rtu(frame)


def from_port(args: argparse.Namespace, stop: Any) -> Iterator[Seen]:
    """Frames heard on a live port until ``stop`` is set; the port is opened here
    (errors now, not at the first frame)."""
    from pyrtu.drivers.port import open_port

    port = open_port(args.port, exclusive=args.exclusive, **serial_kwargs(args))
    return _listen(port, args, stop)


def _listen(port: Any, args: argparse.Namespace, stop: Any) -> Iterator[Seen]:
    from pyrtu.core._backend import active
    from pyrtu.core.ascii import AsciiFramer

    ascii_mode = args.mode == "ascii"
    framer: Any = (
        AsciiFramer("monitor")
        if ascii_mode
        else active.Framer("monitor", rules=_rules(args.profile) or None, **framing_kwargs(args))
    )
    clock = time.monotonic
    try:
        while not stop.is_set():
            now = clock()
            timer = framer.timer()
            wait = 0.05 if timer is None else max(0.0, min(0.05, timer - now))
            data = port.read(wait)
            now = clock()
            if data:
                framer.receive_data(data, now)
            timer = framer.timer()
            if timer is not None and now >= timer:
                framer.handle_timer(now)
            while (ev := framer.next_event()) is not None:
                if ascii_mode:
                    if ev.error is not None:
                        yield Seen("discard", b"", ev.wire, ev.start, ev.error.value)
                    else:
                        yield Seen(str(ev.kind), ev.message, ev.wire, ev.start)
                else:
                    yield _seen_rtu(ev)
    finally:
        port.close()


def example_capture() -> tuple[bytes, list[tuple[int, float]]]:
    """(data, chunks) of a small bus capture at 19200 baud 8E1."""
    from pyrtu.core._backend import active as core

    add = core.add_crc
    t = 10.0
    parts: list[tuple[bytes, float]] = []

    def put(data: bytes, gap: float) -> None:
        nonlocal t
        t += gap + len(data) * 11 / 19200
        parts.append((data, t))

    put(add(bytes.fromhex("010300000002")), 0.0)  # read P0000..P0001 of slave 1
    put(add(bytes.fromhex("010304000a0014")), 0.004)
    put(add(bytes.fromhex("02060064012c")), 0.010)  # write 300 to register 100 of slave 2
    put(add(bytes.fromhex("02060064012c")), 0.004)
    put(b"\x00\xff\x13", 0.010)  # noise on the line
    put(add(bytes.fromhex("0103ffff0001")), 0.010)  # an address that does not exist
    put(add(bytes.fromhex("018302")), 0.004)
    put(add(bytes.fromhex("026401e1")), 0.010)  # Bonfiglioli FC 100, parameter 481
    put(add(bytes.fromhex("026400001388")), 0.004)  # 5000: 50.00 Hz
    frame = add(bytes.fromhex("011000000002040001000a"))
    put(frame[:6], 0.010)  # a USB adapter delivers half a frame ...
    put(frame[6:], 0.016)  # ... and the rest 16 ms later
    put(add(bytes.fromhex("011000000002")), 0.004)
    data = b"".join(p for p, _ in parts)
    chunks = []
    offset = 0
    for p, at in parts:
        chunks.append((offset, at))
        offset += len(p)
    return data, chunks


# -- the command --------------------------------------------------------------------------


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("port", metavar="PORT", nargs="?", help="serial device or pyserial URL")
    src = p.add_mutually_exclusive_group()
    src.add_argument("-c", "--capture", metavar="FILE", help="decode a capture file instead")
    src.add_argument("--example", action="store_true", help="decode a built-in sample capture")
    add_profile_option(p, "decode for this device template (pyrtu template list)")
    add_count_option(p, "stop after N frames (1 or more)")
    add_duration_option(p)
    add_json_option(p, "one JSON line per frame, then a summary line")
    add_serial_options(p, timeout=None)


def _run(args: argparse.Namespace) -> int:
    sources = [args.port is not None, args.capture is not None, args.example]
    if sum(sources) > 1:
        raise ValueError(
            "give a PORT to listen to, or --capture FILE, or --example: not both"
            if sum(sources) == 2 and not args.example
            else "give one of PORT, --capture FILE and --example, not several"
        )
    if sum(sources) == 0:
        raise ValueError("give a PORT to listen to, or --capture FILE, or --example")
    # the built-in sample has Bonfiglioli FC 100 frames
    decoder = Decoder(args.profile, "bonfiglioli" if args.example and not args.profile else None)
    counts: dict[str, int] = {}
    discarded = 0
    shown = 0
    t0: float | None = None
    reader: Any = None
    try:
        # reading a capture may block in open() or read() (a FIFO whose writer has not
        # come or is silent): there a signal interrupts the call (SignalStop)
        with contextlib.suppress(SignalStop), stop_on_signals(args.capture is not None) as stop:
            if args.port is not None:
                frames: Iterable[Seen] = from_port(args, stop)  # opens the port first
                if not args.json:
                    print(
                        f"listening on {args.port} ({args.baudrate} baud {args.bytesize}"
                        f"{args.parity}{args.stopbits:g} {args.mode.upper()}); Ctrl-C to stop",
                        file=sys.stderr,
                        flush=True,
                    )
            elif args.capture is not None:
                reader = open_capture(args.capture)
                frames = from_capture(reader, args.profile, args)
            else:
                frames = from_example(args.profile)
            started = time.monotonic()
            deadline = None if args.duration is None else started + args.duration
            if deadline is not None:
                frames = _until(frames, deadline, stop)
            for seen in frames:
                if t0 is None:
                    t0 = seen.start if seen.start is not None else 0.0
                at = (seen.start or t0) - t0
                decoded = decoder.decode(seen)
                counts[seen.kind] = counts.get(seen.kind, 0) + 1
                if seen.error:
                    discarded += len(seen.raw)
                if args.json:
                    emit(_document(seen, at, decoder, decoded))
                else:
                    print(_line(seen, at, decoder, decoded), flush=True)
                shown += 1
                if args.count is not None and shown >= args.count:
                    break
        warnings = capture_warnings(reader) if reader is not None else []
    finally:
        if reader is not None:
            reader.close()
    for text in warnings:
        print(f"pyrtu sniff: warning: {text}", file=sys.stderr)
    summary: dict[str, Any] = {
        "type": "summary",
        "frames": shown,
        "by_kind": counts,
        "discarded_bytes": discarded,
    }
    if warnings:
        summary["warnings"] = warnings
    if args.json:
        emit(summary)
    else:
        kinds = ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) or "nothing"
        print(f"{shown} frames: {kinds}; {discarded} bytes discarded")
    return EXIT_OK


def _until(frames: Iterable[Seen], deadline: float, stop: Any) -> Iterator[Seen]:
    """The frames until ``deadline`` (a live source also checks between frames)."""

    def timer() -> None:
        while not stop.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                stop.set()
                return
            stop.wait(left)

    import threading

    threading.Thread(target=timer, daemon=True).start()
    for seen in frames:
        if time.monotonic() > deadline:
            return
        yield seen


_NOTE_COLUMN = 60  # device notes go under the frame's summary


def _line(seen: Seen, at: float, decoder: Decoder, d: Decoded) -> str:
    if seen.error:
        line = f"{at:9.4f}s  DISCARD   {d.summary}"
    else:
        name = decoder.function_name(seen.function)
        line = f"{at:9.4f}s  {seen.kind.upper():<9} slave {seen.slave:3d}  {name:<26} {d.summary}"
    for note in d.notes:
        line += f"\n{'':<{_NOTE_COLUMN}}{note}"
    return line


def _document(seen: Seen, at: float, decoder: Decoder, d: Decoded) -> dict[str, Any]:
    doc: dict[str, Any] = {"type": "frame", "t": round(at, 6), "kind": seen.kind}
    if seen.error:
        doc.update(error=seen.error, raw=seen.raw.hex())
        return doc
    doc.update(
        slave=seen.slave,
        function=seen.function & 0x7F,
        function_name=decoder.function_name(seen.function),
        pdu=seen.message[1:].hex(),
        summary=d.summary,
        fields=d.fields,
    )
    if d.notes:
        doc["notes"] = d.notes
    return doc


COMMANDS = (
    subcommand(
        "sniff",
        "decode the traffic of a bus (a live port or a capture), device-aware",
        _configure,
        _run,
        __doc__,
    ),
)
