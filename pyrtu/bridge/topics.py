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
``{prefix}/{edge}/{bus}/{slave}/values``   with ``messages = "device"`` instead: the
                                           slave's changed points, one message per
                                           poll (`device_payload`), not retained
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

In the outbox a value is a point update (`pyrtu.outbox.updates`: the point's
name, value, time, quality; no topic, no JSON of this mode); `Topics.render`
makes it a topic and a payload body (`body`: the payload without its sequence
number and closing brace) when it is published, and `payload` completes it.
With ``messages = "device"`` the records are grouped when published: consecutive
point updates of one slave, no point twice, make one message whose ``points``
object maps each point's name to its own payload (`device_payload`).
An outbox written by an earlier pyrtu (before point updates, issue 33.2) holds
records of the topic, a newline and that body (`split_record`): they are
published as they are, as the pyrtu that wrote them would have.  Every name that
becomes a topic level (the edge, the buses, the points without a ``topic``, and
so the devices whose points' names begin with theirs) is one (`topic_problem`:
no ``/``, no wildcard, no NUL nor other control character); a record that can
never be published (`Unpublishable`: a damaged one, one of a point this
configuration does not have, an older record whose topic no broker accepts) is
set aside by the bridge (`pyrtu.outbox.outbox.Outbox.quarantine`).
"""

from __future__ import annotations

import json
import math
import re
from typing import Protocol

from ..outbox.updates import PointUpdate, UpdateError, decode_update, is_update
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
    @property
    def messages(self) -> str: ...


class _Config(Protocol):
    """What `Topics` reads of a `pyrtu.bridge.config.BridgeConfig`."""

    @property
    def mqtt(self) -> _Mqtt: ...
    @property
    def poller(self) -> PollerConfig: ...
    def option(self, name: str) -> _Options: ...


#: what MQTT forbids in a topic name (3.1.1 and 5.0, 4.7 and 1.5.3/1.5.4): the
#: wildcards, U+0000, UTF-16 surrogates (not UTF-8), and what a receiver may treat as
#: malformed (mosquitto does): the control characters U+0001-U+001F and U+007F-U+009F
#: and the non-characters; a newline would also end a record's topic in the outbox
_NOT_IN_TOPIC = re.compile(
    "[+#\\x00-\\x1f\\x7f-\\x9f\\ud800-\\udfff\\ufdd0-\\ufdef"
    + "".join(f"\\U{plane:04x}fffe\\U{plane:04x}ffff" for plane in range(17))
    + "]"
)
#: the most bytes of a topic name (its UTF-8 length is a 16-bit field)
MAX_TOPIC = 65535


def topic_problem(text: object, *, levels: bool = False) -> str | None:
    """What keeps ``text`` from being one topic level (``levels``: one or more,
    ``/`` between them) of an MQTT topic name, None when nothing: a non-empty
    string with no wildcard (``+`` ``#``), no NUL nor other control character,
    no non-character, at most `MAX_TOPIC` bytes, and, with ``levels``, no empty
    level nor a leading ``$`` (the broker's own topics); without ``levels``, no
    ``/``.  The one rule for every name the bridge puts in a topic."""
    if not isinstance(text, str) or not text:
        return f"must be a non-empty string, not {text!r}"
    bad = _NOT_IN_TOPIC.search(text)
    if bad is not None:
        c = bad.group()
        if c in "+#":
            return f"{text!r} holds the wildcard {c!r}, which no MQTT topic name may hold"
        return (
            f"{text!r} holds U+{ord(c):04X}: an MQTT topic name holds no NUL, "
            "control character or non-character"
        )
    if len(text.encode("utf-8", "surrogatepass")) > MAX_TOPIC:
        return f"is longer than an MQTT topic's {MAX_TOPIC} bytes"
    if not levels:
        if "/" in text:
            return f"{text!r} holds a '/', which would make it more than one topic level"
        return None
    if text.startswith("/") or text.endswith("/") or "//" in text:
        return f"{text!r} has an empty topic level (a / at an end or twice)"
    if text.startswith("$"):
        return f"{text!r} starts with $: such topics are the broker's own"
    return None


QUALITIES = ("good", "stale", "bad")
#: the last level of a slave's device messages' topic (``messages = "device"``)
DEVICE_LEVEL = "values"
ONLINE = b"online"
OFFLINE = b"offline"


class Topics:
    """Every topic of one bridge (ValueError when two would be the same or a name
    that becomes a topic level is not one: `topic_problem`)."""

    def __init__(self, cfg: _Config) -> None:
        m = cfg.mqtt
        self.base = f"{m.prefix}/{m.edge}"
        self.edge_status = f"{self.base}/status"
        self.stats = f"{self.base}/stats"
        #: the filter that catches set commands of the default layout (and typos of them)
        self.set_filter = f"{self.base}/+/+/+/set"
        self.point: dict[str, str] = {}
        self._points: dict[str, Point] = {}
        self.set: dict[str, str] = {}  # set topic -> point name
        self.slave_status: dict[tuple[str, int], str] = {}
        self.bus_status: dict[str, str] = {}
        #: ``messages = "device"``: (bus, slave) -> the topic of its device messages
        self.device: dict[tuple[str, int], str] = {}
        #: ``messages = "device"``: point name -> its slave's device messages' topic
        self.device_of: dict[str, str] = {}
        #: point name -> the name as a JSON string (a key of a device message)
        self.json_name: dict[str, bytes] = {}
        owner: dict[str, str] = {self.edge_status: "the edge status", self.stats: "the stats"}

        def claim(topic: str, what: str) -> None:
            if topic in owner:
                raise ValueError(f"{what}: topic {topic!r} is also {owner[topic]}")
            owner[topic] = what

        for what, text, levels in (("prefix", m.prefix, True), ("edge", m.edge, False)):
            problem = topic_problem(text, levels=levels)
            if problem is not None:
                raise ValueError(f"{what}: {problem}")
        for b in cfg.poller.buses:
            problem = topic_problem(b.name)
            if problem is not None:
                raise ValueError(f"bus {b.name!r}: name: {problem}")
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
            own = cfg.option(p.name).topic
            problem = topic_problem(own, levels=True) if own else topic_problem(p.name)
            if problem is not None:
                raise ValueError(f"point {p.name!r}: {'topic' if own else 'name'}: {problem}")
            t = own or f"{self.base}/{p.bus}/{p.slave}/{p.name}"
            if len((t + "/set/result").encode()) > MAX_TOPIC:
                raise ValueError(f"point {p.name!r}: its topics are longer than {MAX_TOPIC} bytes")
            claim(t, f"point {p.name!r}")
            claim(t + "/set", f"point {p.name!r}'s set topic")
            claim(t + "/set/result", f"point {p.name!r}'s result topic")
            self.point[p.name] = t
            self._points[p.name] = p
            self.set[t + "/set"] = p.name
        if m.messages == "device":
            for bus, slave in self.slave_status:
                t = f"{self.base}/{bus}/{slave}/{DEVICE_LEVEL}"
                claim(t, f"messages: the device messages of slave {slave} on {bus}")
                self.device[(bus, slave)] = t
            for p in cfg.poller.points:
                self.device_of[p.name] = self.device[(p.bus, p.slave)]
                self.json_name[p.name] = json.dumps(p.name, ensure_ascii=False).encode()

    def render_update(self, update: PointUpdate) -> tuple[str, bytes]:
        """(topic, payload body) of a point update; `Unpublishable` for a point this
        configuration does not have (a record of another configuration's run)."""
        point = self._points.get(update.point)
        if point is None:
            raise Unpublishable(
                f"point {update.point!r} is not in this configuration", update.point
            )
        return self.point[update.point], body(point, update.value, update.time, update.quality)

    @staticmethod
    def update(rec: bytes) -> PointUpdate | None:
        """The point update an outbox record holds (None: a record of an earlier
        pyrtu, `split_record`); `Unpublishable` when it is a damaged one."""
        if not is_update(rec):
            return None
        try:
            return decode_update(rec)
        except UpdateError as e:
            raise Unpublishable(str(e), "a damaged point update") from None

    def render(self, rec: bytes) -> tuple[str, bytes]:
        """(topic, payload body) of an outbox record: a point update (`render_update`)
        or a record of an earlier pyrtu (`split_record`); `Unpublishable` when it can
        never be published."""
        update = self.update(rec)
        if update is not None:
            return self.render_update(update)
        problem = unpublishable(rec)
        if problem is not None:
            topic = rec.partition(b"\n")[0].decode("utf-8", "backslashreplace")
            raise Unpublishable(problem, topic)
        return split_record(rec)

    def name(self, rec: bytes) -> str:
        """What a report calls a record: its topic (with ``messages = "device"``, a
        point update's is its slave's device messages'), or what stands for it."""
        try:
            update = self.update(rec)
            if update is not None and update.point in self.device_of:
                return self.device_of[update.point]
            return self.render(rec)[0]
        except Unpublishable as e:
            return e.topic

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


class Unpublishable(ValueError):
    """A record that can never be published: why, and ``topic``, what a report
    calls it (its topic, or what stands for one)."""

    def __init__(self, reason: str, topic: str) -> None:
        super().__init__(reason)
        self.topic = topic


def body(point: Point, value: object, time: float | None, quality: str) -> bytes:
    """A point's payload without its sequence number and closing brace (see the
    module docstring): the value as its shortest faithful decimal
    (`pyrtu.poller.values`); ``time`` None: never read (JSON null)."""
    shown = faithful_value(point, value) if isinstance(value, float) else value
    when = "null" if time is None else repr(time)
    return f'{{"value":{_json_value(shown)},"time":{when},"quality":"{quality}"'.encode()


def split_record(rec: bytes) -> tuple[str, bytes]:
    """(topic, payload body) of an outbox record of an earlier pyrtu (the topic, a
    newline, the body)."""
    nl = rec.index(b"\n")
    return rec[:nl].decode(), rec[nl + 1 :]


def unpublishable(rec: bytes) -> str | None:
    """Why an outbox record of an earlier pyrtu (`split_record`) can never be
    published (None: it can): no topic, or one no broker accepts (`topic_problem`),
    such as a record written by a run whose configuration let a wildcard into a
    point's name."""
    nl = rec.find(b"\n")
    if nl < 0:
        return "no topic (the record has no newline)"
    try:
        topic = rec[:nl].decode("utf-8")
    except UnicodeDecodeError as e:
        return f"its topic is not UTF-8 ({e.reason} at byte {e.start})"
    problem = topic_problem(topic, levels=True)
    return None if problem is None else f"topic {problem}"


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


def device_payload(entries: list[bytes]) -> bytes:
    """A device message's payload: ``{"points":{NAME:PAYLOAD,...}}`` of ``entries``,
    each a point's name as a JSON string, a colon and its point payload (`payload`),
    in sequence order."""
    return b'{"points":{' + b",".join(entries) + b"}}"


__all__ = [
    "DEVICE_LEVEL",
    "MAX_TOPIC",
    "OFFLINE",
    "ONLINE",
    "QUALITIES",
    "Topics",
    "Unpublishable",
    "body",
    "bus_payload",
    "device_payload",
    "payload",
    "split_record",
    "topic_problem",
    "unpublishable",
]
