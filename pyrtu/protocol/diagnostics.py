"""The slave's serial-line state: diagnostic counters, event log, listen-only mode
(FC 07, 08, 11, 12, 17) and the device identification objects (FC 43/14).

Counters as Modbus over Serial Line V1.02 (6.1) and the Bonfiglioli ACT/ACU manual
(6.4.5) define them; the request that reads a counter is counted first (the manual's
example: after "clear counters", reading the slave message count returns 1).
"""

from __future__ import annotations

from collections import deque

from pyrtu import pdu as pdus
from pyrtu.pdu.errors import SlaveException

#: FC 08 sub-function -> counter key
COUNTER_SUBFUNCTIONS = {
    pdus.DIAG_BUS_MESSAGE_COUNT: "bus_message_count",
    pdus.DIAG_BUS_COMM_ERROR_COUNT: "bus_communication_error_count",
    pdus.DIAG_BUS_EXCEPTION_ERROR_COUNT: "slave_exception_error_count",
    pdus.DIAG_SLAVE_MESSAGE_COUNT: "slave_message_count",
    pdus.DIAG_SLAVE_NO_RESPONSE_COUNT: "slave_no_response_count",
    pdus.DIAG_SLAVE_NAK_COUNT: "slave_nak_count",
    pdus.DIAG_SLAVE_BUSY_COUNT: "slave_busy_count",
    pdus.DIAG_BUS_CHAR_OVERRUN_COUNT: "bus_character_overrun_count",
}

# Event log bytes (Application Protocol V1.1b, 6.10).
EVENT_RECEIVE = 0x80
EVENT_RECEIVE_BROADCAST = 0x40
EVENT_RECEIVE_OVERRUN = 0x10
EVENT_RECEIVE_COMM_ERROR = 0x02
EVENT_SEND = 0x40
EVENT_LISTEN_ONLY = 0x20
EVENT_ENTER_LISTEN_ONLY = 0x04
EVENT_RESTART = 0x00

_NOT_COUNTED = frozenset({pdus.GET_COMM_EVENT_COUNTER, pdus.GET_COMM_EVENT_LOG})
_HEX_OR_FRAMING = frozenset(b"0123456789ABCDEFabcdef:\r")


class LineState:
    """Counters, event log and modes of one serial port of a slave."""

    def __init__(self, boundary: float = 0.00175) -> None:
        #: the silence that separates two messages (t3.5 of the line, seconds)
        self.boundary = boundary
        self._error_end: float | None = None
        self.counters = dict.fromkeys(COUNTER_SUBFUNCTIONS.values(), 0)
        self.event_counter = 0
        self.events: deque[int] = deque(maxlen=64)  # newest first
        self.listen_only = False
        self.diagnostic_register = 0
        self.ascii_delimiter = 0x0A
        self.busy = False
        self._comm_error = False
        self._overrun = False

    # ------------------------------------------------------------ bus traffic

    def frame_seen(self) -> None:
        self.counters["bus_message_count"] += 1
        self._error_end = None

    def discard_seen(self, reason: str, start: float | None, end: float | None) -> None:
        """Discarded bytes; the framer may report one damaged message in several
        pieces: pieces with less than a t3.5 silence between them count once."""
        last, self._error_end = self._error_end, end
        if last is not None and start is not None and start - last < self.boundary:
            return
        self.counters["bus_communication_error_count"] += 1
        self._comm_error = True
        if reason == "overflow":
            self.counters["bus_character_overrun_count"] += 1
            self._overrun = True

    def request_received(self, broadcast: bool) -> None:
        self.counters["slave_message_count"] += 1
        event = EVENT_RECEIVE
        if broadcast:
            event |= EVENT_RECEIVE_BROADCAST
        if self.listen_only:
            event |= EVENT_LISTEN_ONLY
        if self._overrun:
            event |= EVENT_RECEIVE_OVERRUN
        if self._comm_error:
            event |= EVENT_RECEIVE_COMM_ERROR
        self._comm_error = self._overrun = False
        self.events.appendleft(event)

    def not_answered(self) -> None:
        self.counters["slave_no_response_count"] += 1

    def completed(self, function: int, times: int = 1) -> None:
        """A request executed without an exception (answered or broadcast); ``times``
        such requests (the TCP server's engine reports them in batches)."""
        if function not in _NOT_COUNTED:
            self.event_counter = (self.event_counter + times) & 0xFFFF

    def answered(self, exception_code: int | None) -> None:
        event = EVENT_SEND | (EVENT_LISTEN_ONLY if self.listen_only else 0)
        if exception_code is not None:
            self.counters["slave_exception_error_count"] += 1
            if exception_code == 6:
                self.counters["slave_busy_count"] += 1
            elif exception_code == 7:
                self.counters["slave_nak_count"] += 1
            if exception_code <= 3:
                event |= 0x01
            elif exception_code == 4:
                event |= 0x02
            elif exception_code in (5, 6):
                event |= 0x04
            elif exception_code == 7:
                event |= 0x08
        self.events.appendleft(event)

    # --------------------------------------------------------------- requests

    def clear(self) -> None:
        for key in self.counters:
            self.counters[key] = 0
        self.diagnostic_register = 0

    def restart(self, clear_log: bool) -> None:
        """Sub-function 0x01: leave listen-only mode, clear the counters (and the log)."""
        self.listen_only = False
        self.clear()
        self.event_counter = 0
        self.ascii_delimiter = 0x0A
        if clear_log:
            self.events.clear()
        self.events.appendleft(EVENT_RESTART)

    def diagnostics(self, request: bytes) -> bytes | None:
        """FC 08: the response PDU, or None when the spec says no response."""
        sub, data = pdus.decode_diagnostics(request)
        if sub == pdus.DIAG_RETURN_QUERY_DATA:
            return request
        if sub == pdus.DIAG_RESTART_COMMUNICATIONS:
            if data not in (0x0000, 0xFF00):
                raise SlaveException(
                    3, f"diagnostics 0x01: data 0x{data:04X} is not 0x0000 or 0xFF00"
                )
            was_listening = self.listen_only
            self.restart(data == 0xFF00)
            return None if was_listening else request
        if sub == pdus.DIAG_CHANGE_ASCII_DELIMITER:
            char, low = data >> 8, data & 0xFF
            if low or char in _HEX_OR_FRAMING:
                raise SlaveException(3, f"diagnostics 0x03: 0x{data:04X} is not a usable delimiter")
            self.ascii_delimiter = char
            return request
        if data != 0:
            if sub in COUNTER_SUBFUNCTIONS or sub in (0x02, 0x04, 0x0A, 0x14):
                raise SlaveException(3, f"diagnostics 0x{sub:02X}: the data field must be 0x0000")
            raise SlaveException(1, f"diagnostics: sub-function 0x{sub:02X} is not supported")
        if sub == pdus.DIAG_RETURN_DIAGNOSTIC_REGISTER:
            return pdus.diagnostics_response(sub, self.diagnostic_register)
        if sub == pdus.DIAG_FORCE_LISTEN_ONLY:
            self.listen_only = True
            self.events.appendleft(EVENT_ENTER_LISTEN_ONLY)
            return None
        if sub == pdus.DIAG_CLEAR_COUNTERS:
            self.clear()
            return request
        if sub == pdus.DIAG_CLEAR_OVERRUN:
            self.counters["bus_character_overrun_count"] = 0
            self._overrun = False
            return request
        key = COUNTER_SUBFUNCTIONS.get(sub)
        if key is None:
            raise SlaveException(1, f"diagnostics: sub-function 0x{sub:02X} is not supported")
        return pdus.diagnostics_response(sub, self.counters[key])

    def event_counter_response(self) -> bytes:
        return pdus.event_counter_response(0xFFFF if self.busy else 0, self.event_counter)

    def event_log_response(self) -> bytes:
        log = pdus.CommEventLog(
            0xFFFF if self.busy else 0,
            self.event_counter,
            self.counters["bus_message_count"],
            list(self.events),
        )
        return pdus.event_log_response(log)


# ------------------------------------------------------------ FC 43/14 objects

#: read code -> the object ids its stream covers (basic, regular, extended)
_STREAM_END = {1: 0x02, 2: 0x7F, 3: 0xFF}


class DeviceIdentification:
    """Device identification objects and their paging into responses.

    Basic objects 0-2 (VendorName, ProductCode, MajorMinorRevision) are
    mandatory; the ones missing get pyrtu defaults.  The conformity level is
    0x81/0x82/0x83 (individual access supported) from the highest category
    present.  Streams (read codes 1-3) start at ``object_id`` (or at 0 when it
    is not an object of the category) and continue with More Follows when the
    objects exceed one response of ``max_pdu`` bytes.
    """

    def __init__(self, objects: dict[int, bytes] | None, max_pdu: int, version: str) -> None:
        self.max_pdu = max_pdu
        defaults = {0: b"pyrtu", 1: b"pyrtu", 2: version.encode()}
        merged = dict(defaults)
        for oid, value in (objects or {}).items():
            if isinstance(oid, bool) or not isinstance(oid, int) or not 0 <= oid <= 0xFF:
                raise ValueError(f"identification: object id must be 0..255, not {oid!r}")
            raw = value.encode() if isinstance(value, str) else bytes(value)
            if len(raw) > max_pdu - 9:
                raise ValueError(
                    f"identification: object {oid} has {len(raw)} bytes, "
                    f"at most {max_pdu - 9} fit a response"
                )
            merged[oid] = raw
        self.objects = dict(sorted(merged.items()))
        top = max(self.objects)
        self.conformity = 0x80 | (3 if top >= 0x80 else 2 if top >= 0x03 else 1)

    def page(self, read_code: int, object_id: int) -> pdus.DeviceIdPage:
        if read_code == 4:
            if object_id not in self.objects:
                raise SlaveException(2, f"read_device_identification: no object {object_id}")
            return pdus.DeviceIdPage(
                4, self.conformity, False, 0, [(object_id, self.objects[object_id])]
            )
        end = _STREAM_END[read_code]
        if object_id not in self.objects or object_id > end:
            object_id = 0
        ids = [oid for oid in self.objects if object_id <= oid <= end]
        room = self.max_pdu - 7
        chosen: list[tuple[int, bytes]] = []
        for oid in ids:
            size = 2 + len(self.objects[oid])
            if size > room:
                return pdus.DeviceIdPage(read_code, self.conformity, True, oid, chosen)
            chosen.append((oid, self.objects[oid]))
            room -= size
        return pdus.DeviceIdPage(read_code, self.conformity, False, 0, chosen)
