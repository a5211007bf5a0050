"""Topic names and payloads (pure functions, no I/O).

Topics, under ``{prefix}/{edge}``:

=========================================  ===============================================
``{prefix}/{edge}/status``                 ``online`` / ``offline`` (the last will), retained
``{prefix}/{edge}/stats``                  the bridge's figures every ``stats_interval``
``{prefix}/{edge}/{bus}/status``           the bus's port: JSON ``{"state": "up"|"down",
                                           "port", "error", "since", "time"}``, retained
``{prefix}/{edge}/{bus}/{slave}/status``   ``online`` / ``offline`` per slave, retained
                                           (``offline`` too while the bus's port is down)
``{prefix}/{edge}/{bus}/{slave}/{point}``  a point's value (or its ``topic``), retained
``{point topic}/set``                      a command to write a writable point
``{point topic}/set/result``               the result when the command names no
                                           MQTT 5 response topic
=========================================  ===============================================

A point's payload is a JSON object: ``{"value": 41.5, "time": 1732550400.123456,
"quality": "good", "seq": 1207}`` where ``time`` is when the value was read off the
wire (the Unix time of the answer's last byte), ``quality`` is ``good``, ``stale``
(the slave stopped answering: the last value read, not a live one) or ``bad``
(the point cannot be read: ``value`` is null), and ``seq`` the edge's sequence
number (from the outbox: strictly increasing across restarts).  A value published
from the backlog after an outage also carries ``"historical": true``.

In the outbox a record is the topic, a newline, and the payload without its
sequence number and closing brace (`record`); `payload` completes it when it is
published.
"""

from __future__ import annotations

import json
import math
from typing import Protocol

from ..poller import Point, PollerConfig
from ..poller.values import faithful_value


class _Options(Protocol):
    @property
    def topic(self) -> str | None: ...


class _Mqtt(Protocol):
    @property
    def prefix(self) -> str: ...
    @property
    def edge(self) -> str: ...


class _Config(Protocol):
    """What `Topics` reads of a `pyrtu.bridge.config.BridgeConfig`."""

    @property
    def mqtt(self) -> _Mqtt: ...
    @property
    def poller(self) -> PollerConfig: ...
    def option(self, name: str) -> _Options: ...


QUALITIES = ("good", "stale", "bad")
ONLINE = b"online"
OFFLINE = b"offline"


class Topics:
    """Every topic of one bridge (ValueError when two would be the same or a bus
    name is not one topic level)."""

    def __init__(self, cfg: _Config) -> None:
        m = cfg.mqtt
        self.base = f"{m.prefix}/{m.edge}"
        self.edge_status = f"{self.base}/status"
        self.stats = f"{self.base}/stats"
        #: the filter that catches set commands of the default layout (and typos of them)
        self.set_filter = f"{self.base}/+/+/+/set"
        self.point: dict[str, str] = {}
        self.set: dict[str, str] = {}  # set topic -> point name
        self.slave_status: dict[tuple[str, int], str] = {}
        self.bus_status: dict[str, str] = {}
        owner: dict[str, str] = {self.edge_status: "the edge status", self.stats: "the stats"}

        def claim(topic: str, what: str) -> None:
            if topic in owner:
                raise ValueError(f"{what}: topic {topic!r} is also {owner[topic]}")
            owner[topic] = what

        for b in cfg.poller.buses:
            if "/" in b.name or "+" in b.name or "#" in b.name or "\n" in b.name:
                raise ValueError(f"bus {b.name!r}: a bus name is one topic level (no / + #)")
            t = f"{self.base}/{b.name}/status"
            claim(t, f"bus {b.name}'s status")
            self.bus_status[b.name] = t
        for p in cfg.poller.points:
            key = (p.bus, p.slave)
            if key not in self.slave_status:
                t = f"{self.base}/{p.bus}/{p.slave}/status"
                claim(t, f"slave {p.slave} on {p.bus}'s status")
                self.slave_status[key] = t
        for p in cfg.poller.points:
            t = cfg.option(p.name).topic or f"{self.base}/{p.bus}/{p.slave}/{p.name}"
            claim(t, f"point {p.name!r}")
            claim(t + "/set", f"point {p.name!r}'s set topic")
            claim(t + "/set/result", f"point {p.name!r}'s result topic")
            self.point[p.name] = t
            self.set[t + "/set"] = p.name

    def extra_set_topics(self) -> list[str]:
        """The set topics `set_filter` does not catch (overridden topics)."""
        lead = self.base.count("/") + 1
        return [
            t for t in self.set if not (t.startswith(self.base + "/") and t.count("/") == lead + 3)
        ]


def _json_value(value: object) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "null"
    if value is True:
        return "true"
    if value is False:
        return "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    return json.dumps(value, ensure_ascii=False)


def record(topic: str, point: Point, value: object, time: float, quality: str) -> bytes:
    """The outbox record of a point's value (see the module docstring): the value as
    its shortest faithful decimal (`pyrtu.poller.values`)."""
    shown = faithful_value(point, value) if isinstance(value, float) else value
    return (
        f'{topic}\n{{"value":{_json_value(shown)},"time":{time!r},"quality":"{quality}"'
    ).encode()


def split_record(rec: bytes) -> tuple[str, bytes]:
    """(topic, payload without seq and closing brace) of an outbox record."""
    nl = rec.index(b"\n")
    return rec[:nl].decode(), rec[nl + 1 :]


def bus_payload(state: str, port: str, error: str, since: float | None, time: float) -> bytes:
    """A bus status: ``state`` ``up`` or ``down``, the port, the outage's error
    (``""`` when none), when the outage began (null when up and none was seen)."""
    return json.dumps(
        {"state": state, "port": port, "error": error, "since": since, "time": time}
    ).encode()


def payload(body: bytes, seq: int, historical: bool) -> bytes:
    """The published payload of a record's body."""
    if historical:
        return body + b',"seq":%d,"historical":true}' % seq
    return body + b',"seq":%d}' % seq


__all__ = [
    "OFFLINE",
    "ONLINE",
    "QUALITIES",
    "Topics",
    "bus_payload",
    "payload",
    "record",
    "split_record",
]
