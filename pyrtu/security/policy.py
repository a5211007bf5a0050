"""The access policy of a listener: who may do what, sans-I/O.

MODBUS/TCP Security (v36, 2021) authorizes every request by the client's role and
answers a request the role may not make with exception 01 (ILLEGAL FUNCTION).  Here
the same holds on plain Modbus TCP too, where the client is known by its address.

A `Policy` is a list of `Rule`; a rule names whom it is for (``roles``: the roles of
TLS client certificates; ``clients``: address ranges) and what they may do: unit ids,
function codes, tables with address ranges, read-only.  A request is allowed when one
rule that matches its client allows it; else `Policy.decide` says why not (the first
matching rule's reason, or that no rule is for this client).  Nothing here touches a
socket or a clock: `decide` is a function of (identity, unit, request PDU)::

    policy = Policy([Rule("readers", clients=(ip_network("10.0.0.0/8"),), read_only=True)])
    decision = policy.decide(Identity("10.1.2.3"), 1, bytes.fromhex("0300000002"))
    decision.allowed                                  # True

Reads are the functions that change nothing in a device (`is_read`): 1-4, 7, 11,
12, 17, 20, 24, 43/14 and the diagnostics sub-functions that only report (0, 2,
11-18).  Anything else (writes, restarts, clearing counters, user-defined function
codes) is a write for ``read_only`` and for the audit trail.
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from pyrtu.core._text import number_ranges
from pyrtu.pdu.functions import (
    DIAGNOSTICS,
    ENCAPSULATED_INTERFACE,
    MASK_WRITE_REGISTER,
    MEI_DEVICE_ID,
    READ_COILS,
    READ_DISCRETE_INPUTS,
    READ_FIFO_QUEUE,
    READ_FILE_RECORD,
    READ_HOLDING_REGISTERS,
    READ_INPUT_REGISTERS,
    READ_WRITE_REGISTERS,
    WRITE_FILE_RECORD,
    WRITE_MULTIPLE_COILS,
    WRITE_MULTIPLE_REGISTERS,
    WRITE_SINGLE_COIL,
    WRITE_SINGLE_REGISTER,
)

Network = ipaddress.IPv4Network | ipaddress.IPv6Network

#: the four tables of the data model, by their policy-file names
TABLES = ("coils", "discrete_inputs", "holding_registers", "input_registers")
#: the functions that only read (with their sub-function checks in `is_read`)
READ_FUNCTIONS = frozenset({1, 2, 3, 4, 7, 11, 12, 17, 20, 24})
#: the diagnostics sub-functions that only report (Application Protocol 6.8)
READ_DIAGNOSTICS = frozenset({0, 2, *range(11, 19)})
#: the words in a FIFO queue read (its count register and up to 31 values)
FIFO_WORDS = 32

_TABLE_OF_READ = {
    READ_COILS: "coils",
    READ_DISCRETE_INPUTS: "discrete_inputs",
    READ_HOLDING_REGISTERS: "holding_registers",
    READ_INPUT_REGISTERS: "input_registers",
}
_WORD = struct.Struct(">H")
_PAIR = struct.Struct(">HH")


@dataclass(frozen=True)
class Identity:
    """Who sent a request: the client's address (and port), and on TLS the role and
    subject of its certificate."""

    address: str
    port: int | None = None
    role: str | None = None
    subject: str | None = None

    @property
    def tls(self) -> bool:
        return self.subject is not None

    def ip(self) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
        """The address as an IP address (an IPv4-mapped IPv6 one as IPv4), None if
        it is none (a Unix socket)."""
        try:
            ip = ipaddress.ip_address(self.address.split("%", 1)[0])
        except ValueError:
            return None
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            return ip.ipv4_mapped
        return ip

    def describe(self) -> str:
        """For the log: ``10.0.0.5`` or ``10.0.0.5 (role "operator", CN=panel1)``."""
        if not self.tls:
            return self.address
        role = "no role" if self.role is None else f'role "{self.role}"'
        return f"{self.address} ({role}, {self.subject})"


@dataclass(frozen=True)
class Access:
    """A range of one table a request reads or writes."""

    table: str
    start: int
    count: int
    write: bool

    @property
    def end(self) -> int:
        """The last address (inclusive)."""
        return self.start + self.count - 1


class Unplaceable(ValueError):
    """A request whose addresses cannot be placed in the four tables (a file record,
    or a PDU too short to carry its addresses)."""


def is_read(pdu: bytes) -> bool:
    """Whether the request only reads (see the module docstring)."""
    if not pdu:
        return False
    function = pdu[0]
    if function in READ_FUNCTIONS:
        return True
    if function == DIAGNOSTICS:
        return len(pdu) >= 3 and _WORD.unpack_from(pdu, 1)[0] in READ_DIAGNOSTICS
    if function == ENCAPSULATED_INTERFACE:
        return len(pdu) >= 2 and pdu[1] == MEI_DEVICE_ID
    return False


def accesses(pdu: bytes) -> tuple[Access, ...]:
    """The table ranges the request ``pdu`` reads and writes (empty: it touches none,
    as diagnostics or identification).  `Unplaceable` when they cannot be known."""
    function = pdu[0]
    size = len(pdu)
    if function in _TABLE_OF_READ or function in (WRITE_MULTIPLE_COILS, WRITE_MULTIPLE_REGISTERS):
        if size < 5:
            raise Unplaceable("too short for its address and quantity")
        start, count = _PAIR.unpack_from(pdu, 1)
        if function in _TABLE_OF_READ:
            return (Access(_TABLE_OF_READ[function], start, count, False),)
        table = "coils" if function == WRITE_MULTIPLE_COILS else "holding_registers"
        return (Access(table, start, count, True),)
    if function in (WRITE_SINGLE_COIL, WRITE_SINGLE_REGISTER, MASK_WRITE_REGISTER):
        if size < 3:
            raise Unplaceable("too short for its address")
        table = "coils" if function == WRITE_SINGLE_COIL else "holding_registers"
        return (Access(table, _WORD.unpack_from(pdu, 1)[0], 1, True),)
    if function == READ_WRITE_REGISTERS:
        if size < 9:
            raise Unplaceable("too short for its addresses and quantities")
        read_start, read_count, write_start, write_count = struct.unpack_from(">HHHH", pdu, 1)
        return (
            Access("holding_registers", read_start, read_count, False),
            Access("holding_registers", write_start, write_count, True),
        )
    if function == READ_FIFO_QUEUE:
        if size < 3:
            raise Unplaceable("too short for its pointer")
        pointer = _WORD.unpack_from(pdu, 1)[0]
        return (Access("holding_registers", pointer, min(FIFO_WORDS, 65536 - pointer), False),)
    if function in (READ_FILE_RECORD, WRITE_FILE_RECORD):
        raise Unplaceable("file records are outside the four tables")
    return ()


def parse_ranges(text: str) -> tuple[range, ...]:
    """``"0-99,200,300-309"`` as ranges (inclusive bounds 0..65535); ValueError."""
    return number_ranges(
        text,
        0,
        65535,
        not_a_range="expected ADDRESS or FIRST-LAST, not {part!r}",
        outside="expected addresses 0..65535, first <= last, not {part!r}",
    )


@dataclass(frozen=True)
class Decision:
    """Whether a request may run; when not, ``kind`` (a metric label: no_rule, unit,
    function, table, address, read_only, unplaceable) and ``reason`` (for the log)."""

    allowed: bool
    kind: str = ""
    reason: str = ""


ALLOWED = Decision(True)
#: every `Decision.kind` of a refusal (the labels of the metrics)
REFUSAL_KINDS = ("no_rule", "unit", "function", "read_only", "table", "address", "unplaceable")


@dataclass(frozen=True)
class Rule:
    """Whom a rule is for (``roles``, ``clients``; both given: both must match) and
    what they may do (None: no limit)."""

    name: str
    roles: frozenset[str] | None = None
    clients: tuple[Network, ...] | None = None
    units: frozenset[int] | None = None
    functions: frozenset[int] | None = None
    #: table -> the address ranges allowed in it; a table not named is refused
    tables: Mapping[str, tuple[range, ...]] | None = None
    read_only: bool = False

    def __post_init__(self) -> None:
        if self.roles is None and self.clients is None:
            raise ValueError(f"{self.name}: a rule needs roles or clients (whom it is for)")

    def matches(self, identity: Identity) -> bool:
        if self.roles is not None and identity.role not in self.roles:
            return False
        if self.clients is not None:
            ip = identity.ip()
            if ip is None or not any(ip.version == n.version and ip in n for n in self.clients):
                return False
        return True

    def permits(self, unit: int, pdu: bytes) -> Decision:
        """Whether this rule lets its clients send ``pdu`` to ``unit``."""
        function = pdu[0]
        if self.units is not None and unit not in self.units:
            return Decision(False, "unit", f"unit {unit} is not allowed by {self.name}")
        if self.functions is not None and function not in self.functions:
            return Decision(False, "function", f"function {function} is not allowed by {self.name}")
        if self.read_only and not is_read(pdu):
            return Decision(
                False, "read_only", f"function {function} writes ({self.name} reads only)"
            )
        if self.tables is None:
            return ALLOWED
        try:
            ranges = accesses(pdu)
        except Unplaceable as exc:
            return Decision(False, "unplaceable", f"function {function}: {exc} ({self.name})")
        for access in ranges:
            allowed = self.tables.get(access.table)
            if allowed is None:
                return Decision(False, "table", f"{access.table} are not allowed by {self.name}")
            if access.count < 1 or not any(access.start in r and access.end in r for r in allowed):
                what = "writes" if access.write else "reads"
                return Decision(
                    False,
                    "address",
                    f"{what} {access.table} {access.start}-{access.end}: outside {self.name}",
                )
        return ALLOWED

    def restricted_to_reads(self) -> Rule:
        return Rule(
            self.name, self.roles, self.clients, self.units, self.functions, self.tables, True
        )


@dataclass(frozen=True)
class Policy:
    """The rules of a listener (``source``: where they came from, for the log)."""

    rules: Sequence[Rule]
    source: str = "policy"

    def decide(self, identity: Identity, unit: int, pdu: bytes) -> Decision:
        """Whether ``identity`` may send the request ``pdu`` to ``unit``."""
        refusal: Decision | None = None
        for rule in self.rules:
            if not rule.matches(identity):
                continue
            decision = rule.permits(unit, pdu)
            if decision.allowed:
                return decision
            refusal = refusal or decision
        if refusal is not None:
            return refusal
        who = f'role "{identity.role}"' if identity.role is not None else "this client"
        if identity.tls and identity.role is None:
            who = "a certificate without a role"
        return Decision(False, "no_rule", f"no rule of {self.source} is for {who}")

    def restricted_to_reads(self) -> Policy:
        """The same rules, each read-only (``--policy`` with ``--read-only``)."""
        return Policy([r.restricted_to_reads() for r in self.rules], f"{self.source}, read-only")

    @classmethod
    def read_only(cls) -> Policy:
        """Every client may read anything and write nothing (``--read-only``)."""
        everyone = (ipaddress.ip_network("0.0.0.0/0"), ipaddress.ip_network("::/0"))
        return cls([Rule("--read-only", clients=everyone, read_only=True)], "--read-only")


def beyond_loopback(host: str) -> bool:
    """Whether a listener on ``host`` can be reached from other machines (any address
    but a loopback one, ``localhost`` included)."""
    if host == "localhost":
        return False
    try:
        return not ipaddress.ip_address(host.split("%", 1)[0]).is_loopback
    except ValueError:  # "" (every address) or a host name
        return True


def networks(items: Iterable[str]) -> tuple[Network, ...]:
    """Address ranges (``10.0.0.0/8``, ``192.168.1.7``, ``::1``); ValueError."""
    result = []
    for item in items:
        try:
            result.append(ipaddress.ip_network(item.strip(), strict=False))
        except ValueError:
            raise ValueError(
                f"expected an address or a range like 10.0.0.0/8, not {item!r}"
            ) from None
    return tuple(result)


__all__ = [
    "ALLOWED",
    "READ_DIAGNOSTICS",
    "READ_FUNCTIONS",
    "REFUSAL_KINDS",
    "TABLES",
    "Access",
    "Decision",
    "Identity",
    "Policy",
    "Rule",
    "Unplaceable",
    "accesses",
    "beyond_loopback",
    "is_read",
    "networks",
    "parse_ranges",
]
