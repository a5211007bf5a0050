"""The audit trail of writes (``--audit FILE|-``): every write a listener executed, as
one JSON line: who (address, and on TLS the certificate's subject and role), the unit,
the function, the addresses and values, when (UTC, ISO 8601) and the result::

    {"time": "2026-11-28T14:31:02.123456+00:00", "client": "10.0.0.5", "port": 50012,
     "role": "operator", "subject": "CN=panel1", "unit": 1, "function": 16,
     "name": "write_registers", "address": 100, "values": [1, 2], "result": "ok"}

A write is what `pyrtu.security.policy.is_read` says is not a read.  ``result``:
``ok``, ``exception 0x02`` (the device's, or the gateway's own 0x0B when the device
did not answer), ``broadcast`` (unit 0: no answer comes).  `audit_record` is pure;
`AuditTrail` writes the lines, flushed one by one.
"""

from __future__ import annotations

import datetime
import json
import struct
import sys
from pathlib import Path
from typing import Any, TextIO

from pyrtu.pdu.functions import (
    MASK_WRITE_REGISTER,
    READ_WRITE_REGISTERS,
    WRITE_MULTIPLE_COILS,
    WRITE_MULTIPLE_REGISTERS,
    WRITE_SINGLE_COIL,
    WRITE_SINGLE_REGISTER,
    function_name,
)

from .policy import Identity


def _registers(pdu: bytes, at: int) -> dict[str, Any] | None:
    """The registers a write carries from ``at``: address, count, byte count, then the
    values (FC 16; FC 23's write half); None when the counts do not match the PDU."""
    address, count, nbytes = struct.unpack_from(">HHB", pdu, at)
    if nbytes != 2 * count or len(pdu) != at + 5 + nbytes:
        return None
    return {"address": address, "values": list(struct.unpack_from(f">{count}H", pdu, at + 5))}


def _values(pdu: bytes) -> dict[str, Any]:
    """The addresses and values a write carries (the PDU in hex when it is no
    write this module knows, or too short)."""
    function, size = pdu[0], len(pdu)
    try:
        if function == WRITE_SINGLE_COIL and size == 5:
            address, value = struct.unpack_from(">HH", pdu, 1)
            coil: bool | int = {0xFF00: True, 0x0000: False}.get(value, value)
            return {"address": address, "values": [coil]}
        if function == WRITE_SINGLE_REGISTER and size == 5:
            address, value = struct.unpack_from(">HH", pdu, 1)
            return {"address": address, "values": [value]}
        if function == WRITE_MULTIPLE_COILS and size >= 6:
            address, count, nbytes = struct.unpack_from(">HHB", pdu, 1)
            data = pdu[6 : 6 + nbytes]
            if len(data) == nbytes and count <= nbytes * 8:
                bits = [bool(data[i // 8] >> (i % 8) & 1) for i in range(count)]
                return {"address": address, "values": bits}
        if function == WRITE_MULTIPLE_REGISTERS and size >= 6:
            return _registers(pdu, 1) or {"pdu": pdu.hex()}
        if function == MASK_WRITE_REGISTER and size == 7:
            address, and_mask, or_mask = struct.unpack_from(">HHH", pdu, 1)
            return {"address": address, "and_mask": and_mask, "or_mask": or_mask}
        if function == READ_WRITE_REGISTERS and size >= 10:
            return _registers(pdu, 5) or {"pdu": pdu.hex()}
    except struct.error:  # pragma: no cover - the sizes are checked above
        pass
    return {"pdu": pdu.hex()}


def result_of(unit: int, answer: bytes | None) -> str:
    if answer is None:
        return "broadcast" if unit == 0 else "no answer"
    if answer[0] & 0x80:
        code = answer[1] if len(answer) > 1 else 0
        return f"exception 0x{code:02x}"
    return "ok"


def audit_record(
    identity: Identity, unit: int, pdu: bytes, answer: bytes | None, when: float
) -> dict[str, Any]:
    """The audit line of an executed write (``when``: a POSIX time)."""
    stamp = datetime.datetime.fromtimestamp(when, datetime.timezone.utc).isoformat()
    record: dict[str, Any] = {"time": stamp, "client": identity.address, "port": identity.port}
    if identity.tls:
        record.update(role=identity.role, subject=identity.subject)
    record.update(unit=unit, function=pdu[0], name=function_name(pdu[0]))
    record.update(_values(pdu))
    record["result"] = result_of(unit, answer)
    return record


class AuditTrail:
    """Writes audit records as JSON lines to ``stream`` (flushed at each line);
    ``records``: how many were written."""

    def __init__(self, stream: TextIO, name: str = "-", owned: bool = False) -> None:
        self.stream = stream
        self.name = name
        self._owned = owned
        self.records = 0

    @classmethod
    def open(cls, target: str | Path) -> AuditTrail:
        """``-``: stderr; else a file, appended to (OSError when it cannot be)."""
        if str(target) == "-":
            return cls(sys.stderr)
        stream = open(target, "a", encoding="utf-8")
        return cls(stream, str(target), owned=True)

    def write(self, record: dict[str, Any]) -> None:
        self.stream.write(json.dumps(record, separators=(", ", ": ")) + "\n")
        self.stream.flush()
        self.records += 1

    def record(
        self, identity: Identity, unit: int, pdu: bytes, answer: bytes | None, when: float
    ) -> None:
        self.write(audit_record(identity, unit, pdu, answer, when))

    def close(self) -> None:
        if self._owned and not self.stream.closed:
            self.stream.close()


__all__ = ["AuditTrail", "audit_record", "result_of"]
