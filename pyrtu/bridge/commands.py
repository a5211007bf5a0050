"""Set commands: parsing, checks, expiry, de-duplication and rate limits (sans-I/O).

A command is a message on ``{point topic}/set`` whose payload is JSON: a bare
value (``42.5``, ``true``, ``"text"``) or an object ``{"value": 42.5, "id":
"c-17", "time": 1732550400.5}``.  ``id`` makes it idempotent (a repeat with the
same id is executed once; its result is sent again); ``time`` (when the sender
made it, Unix) makes it expire ``command_expiry`` seconds later even if the
broker delivered it late.  Every command expires: at its MQTT 5 message expiry
if it has one, else ``command_expiry`` seconds after it arrived; an expired
command is answered ``expired`` and never written.

Before a byte is sent the value is checked against the point's type, its scale
(the raw value must fit the register: an unscaled integer point takes only whole
numbers, a scaled one rounds to its resolution and the result says so; the rule of
`pyrtu.poller.points.encode_point_value`, `Poller.write`'s too) and its
``min``/``max``; a retained command, an oversized payload, a point that is not
writable and a topic that names no point are refused with a result saying why.
An empty payload is no command: it is what clearing a retained message delivers
(``mosquitto_pub -r -n``), and it is ignored (`parse` returns None).
"""

from __future__ import annotations

import json
import math
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

from ..poller import Point
from ..poller.points import Encoded, encode_point_value


@dataclass(slots=True)
class SetCommand:
    """An accepted command, waiting for its slave's turn."""

    point: Point
    value: Any  # as the register holds it (a scaled point's, rounded to its resolution)
    id: str | None
    expires: float  # on the driver's clock
    received: float
    reply_to: str
    correlation: bytes | None = None
    sent: float | None = None  # the sender's "time" (Unix), when it gave one
    rounded: dict[str, Any] | None = None  # the result's "rounded": asked, written, step


@dataclass(frozen=True, slots=True)
class Refusal:
    """A command refused before it was queued: ``error`` is the result's kind."""

    error: str
    message: str
    id: str | None = None


def result(
    point: str | None,
    ok: bool,
    *,
    id: str | None = None,
    error: str | None = None,
    message: str | None = None,
    value: Any = None,
    time: float | None = None,
    exception_code: int | None = None,
    rounded: dict[str, Any] | None = None,
    method: str | None = None,
) -> bytes:
    """The JSON of a result: ``{"ok": true, "point", "id", "value", "time"}`` (the
    value read back after the write, null where that is not a number, as on the
    point's topic; with ``"rounded": {"requested", "written",
    "resolution"}`` when a scaled point took the value rounded to its resolution, and
    ``"method"``, ``mask_write`` (FC 22) or ``read_modify_write``, for a bit or field
    of a register) or
    ``{"ok": false, "point", "id", "error", "message"}``; ``error`` is one of
    ``malformed``, ``too_large``, ``retained``, ``unknown_point``, ``not_writable``,
    ``validation``, ``expired``, ``busy``, ``exception`` (with ``exception_code``),
    ``timeout``, ``failed``."""
    doc: dict[str, Any] = {"ok": ok, "point": point}
    if id is not None:
        doc["id"] = id
    if ok:  # a value read back that is not a number (NaN, infinite): null, as on its topic
        finite = not isinstance(value, float) or math.isfinite(value)
        doc["value"] = value if finite else None
        doc["time"] = time
        if rounded is not None:
            doc["rounded"] = rounded
        if method is not None:
            doc["method"] = method
    else:
        doc["error"] = error
        doc["message"] = message
        if exception_code is not None:
            doc["exception_code"] = exception_code
    return json.dumps(doc, allow_nan=False, default=str).encode()


def check_value(point: Point, value: object) -> Encoded:
    """``value`` as the point's registers take it (`Encoded`: what they will hold,
    and whether that is ``value`` rounded; a bit's or field's FC 22 mask); ValueError
    saying why not (nothing sent): a JSON type the point does not take, a label
    not among its enum's, a number outside its ``min``..``max`` or its registers,
    a text longer than its registers."""
    if point.labels:
        if isinstance(value, bool) or not isinstance(value, str | int):
            raise ValueError(
                f"value must be one of {', '.join(json.dumps(x) for x in point.labels)},"
                f" not {json.dumps(value)}"
            )
    elif point.type == "bool":
        if not isinstance(value, bool) and not (
            isinstance(value, int) and not isinstance(value, bool) and value in (0, 1)
        ):
            raise ValueError(f"value must be true or false (or 0/1), not {value!r}")
        value = bool(value)
    elif point.type in ("string", "string1"):
        if not isinstance(value, str):
            raise ValueError(f"value must be a string, not {json.dumps(value)}")
    else:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"value must be a number, not {json.dumps(value)}")
        if not math.isfinite(value):
            raise ValueError("value must be a finite number")
        if point.min is not None and value < point.min:
            raise ValueError(f"value {value!r} is below the point's min {point.min!r}")
        if point.max is not None and value > point.max:
            raise ValueError(f"value {value!r} is above the point's max {point.max!r}")
    encoded = encode_point_value(point, value)  # scale, offset, the register's range
    return encoded


def rounding(point: Point, requested: object, encoded: Encoded) -> dict[str, Any] | None:
    """The result's ``rounded`` when a scaled point took ``requested`` rounded."""
    if not encoded.rounded:
        return None
    return {"requested": requested, "written": encoded.value, "resolution": abs(point.scale)}


def parse(
    payload: bytes, *, max_payload: int, retained: bool
) -> tuple[Any, str | None, float | None] | Refusal | None:
    """(value, id, time) of a command's payload, or the `Refusal`; None for an
    empty payload (a retained command being cleared: no command, no answer)."""
    if not payload:
        return None
    if len(payload) > max_payload:
        return Refusal("too_large", f"payload of {len(payload)} bytes; at most {max_payload}")
    try:
        doc = json.loads(payload.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError) as e:
        return Refusal("malformed", f"not JSON: {e}")
    cid: str | None = None
    sent: float | None = None
    if isinstance(doc, dict):
        unknown = sorted(set(doc) - {"value", "id", "time"})
        raw_id = doc.get("id")
        if raw_id is not None and not isinstance(raw_id, str | int):
            return Refusal("malformed", "id must be a string or an integer")
        cid = None if raw_id is None else str(raw_id)
        if unknown:
            return Refusal("malformed", f"unknown key {unknown[0]!r} (keys: value, id, time)", cid)
        if "value" not in doc:
            return Refusal("malformed", 'no "value"', cid)
        t = doc.get("time")
        if t is not None:
            if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t):
                return Refusal("malformed", "time must be a Unix time in seconds", cid)
            sent = float(t)
        doc = doc["value"]
    elif isinstance(doc, list):
        return Refusal("malformed", "a value or an object {value, id, time}, not a list")
    if retained:
        return Refusal(
            "retained",
            "retained set messages are refused (a setpoint is never "
            "replayed); publish without the retain flag",
            cid,
        )
    return doc, cid, sent


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON value")


class TokenBucket:
    """``rate`` writes per second with bursts of ``burst``; `wait` says how long
    until the next may go (0: now) and takes the token when it is 0."""

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate = rate
        self.burst = burst
        self.tokens = burst
        self.t = now

    def wait(self, now: float) -> float:
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now
        if self.tokens >= 1:
            self.tokens -= 1
            return 0.0
        return (1 - self.tokens) / self.rate


@dataclass
class CommandQueue:
    """Commands waiting per slave (at most ``size`` in all), the per-slave rate
    limits and the ids seen lately (for idempotence)."""

    size: int
    rate: float
    remember: int = 4096
    queues: dict[tuple[str, int], deque[SetCommand]] = field(default_factory=dict)
    buckets: dict[tuple[str, int], TokenBucket] = field(default_factory=dict)
    seen: OrderedDict[str, bytes | None] = field(default_factory=OrderedDict)
    waiting: int = 0
    refused: int = 0
    expired: int = 0
    executed: int = 0
    duplicates: int = 0

    def known(self, cid: str | None) -> tuple[bool, bytes | None]:
        """(seen before, its result if it has one)."""
        if cid is None or cid not in self.seen:
            return False, None
        self.seen.move_to_end(cid)
        self.duplicates += 1
        return True, self.seen[cid]

    def push(self, cmd: SetCommand) -> bool:
        """Queue a command; False when the queue is full (the caller refuses it)."""
        if self.waiting >= self.size:
            self.refused += 1
            return False
        key = (cmd.point.bus, cmd.point.slave)
        self.queues.setdefault(key, deque()).append(cmd)
        self.waiting += 1
        if cmd.id is not None:
            self.seen[cmd.id] = None
            while len(self.seen) > self.remember:
                self.seen.popitem(last=False)
        return True

    def pop(self, key: tuple[str, int]) -> SetCommand | None:
        q = self.queues.get(key)
        if not q:
            return None
        self.waiting -= 1
        return q.popleft()

    def bucket(self, key: tuple[str, int], now: float) -> TokenBucket:
        b = self.buckets.get(key)
        if b is None:
            b = self.buckets[key] = TokenBucket(self.rate, max(1.0, min(self.rate, 4.0)), now)
        return b

    def done(self, cid: str | None, res: bytes) -> None:
        if cid is not None and cid in self.seen:
            self.seen[cid] = res


__all__ = [
    "CommandQueue",
    "Refusal",
    "SetCommand",
    "TokenBucket",
    "check_value",
    "parse",
    "result",
    "rounding",
]
