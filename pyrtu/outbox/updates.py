"""A point update as an outbox record, in no output's shape (sans-I/O).

Every output (the JSON bridge, the Sparkplug edge node) appends `encode_update`
records and reads them back with `decode_update`; what it publishes (a topic and a
payload, an alias) is its own business, derived when it publishes, so that a
record outlives a change of the output's naming and a backlog one output left is
published by another.  A record is::

    b"\\x00pu1" JSON [point name, value, time read, quality]

The leading NUL tells it from the records of earlier pyrtus' JSON bridge, which
begin with an MQTT topic (and no topic holds a NUL). ``value``: a bool, int, float
(NaN and the infinities as JSON's extensions), str or null; ``time``: Unix seconds
or null (never read); ``quality``: ``good``, ``stale`` or ``bad``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from ..poller.points import Value

#: the first bytes of a point update record (format 1)
UPDATE_MARK = b"\x00pu1"
QUALITIES = ("good", "stale", "bad")


class UpdateError(ValueError):
    """A record that is no point update (or a damaged one)."""


@dataclass(frozen=True, slots=True)
class PointUpdate:
    """A point's value: ``time`` when it was read (Unix; None: never), ``quality``
    one of `QUALITIES`."""

    point: str
    value: Value | None
    time: float | None
    quality: str


#: ``json.dumps(x, separators=(",", ":"), ensure_ascii=False)``, its encoder made
#: once (`json.dumps` makes one per call when given options: a record per update)
_COMPACT = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False).encode


def encode_update(update: PointUpdate) -> bytes:
    """The outbox record of ``update``."""
    if update.quality not in QUALITIES:
        raise ValueError(f"quality must be one of {', '.join(QUALITIES)}, not {update.quality!r}")
    body = [update.point, update.value, update.time, update.quality]
    return UPDATE_MARK + _COMPACT(body).encode()


def is_update(record: bytes) -> bool:
    return record.startswith(UPDATE_MARK)


def decode_update(record: bytes) -> PointUpdate:
    """The point update a record holds; `UpdateError` if it holds none."""
    if not is_update(record):
        raise UpdateError("not a point update record (no leading mark)")
    try:
        body = json.loads(record[len(UPDATE_MARK) :].decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise UpdateError(f"a damaged point update record: {e}") from None
    if not (isinstance(body, list) and len(body) == 4):
        raise UpdateError("a point update record holds [point, value, time, quality]")
    point, value, time, quality = body
    if not isinstance(point, str) or quality not in QUALITIES:
        raise UpdateError(f"a point update record with a bad point or quality: {body!r}")
    if value is not None and not isinstance(value, (bool, int, float, str)):
        raise UpdateError(f"a point update record with a bad value: {value!r}")
    if time is not None and (
        isinstance(time, bool) or not isinstance(time, (int, float)) or not math.isfinite(time)
    ):
        raise UpdateError(f"a point update record with a bad time: {time!r}")
    return PointUpdate(point, value, None if time is None else float(time), quality)


__all__ = [
    "QUALITIES",
    "UPDATE_MARK",
    "PointUpdate",
    "UpdateError",
    "decode_update",
    "encode_update",
    "is_update",
]
