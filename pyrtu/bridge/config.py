"""The bridge's configuration: the poller's TOML plus an ``[mqtt]`` table and
per-point keys.

::

    [mqtt]
    url = "mqtt://localhost:1883"      # or mqtts://host:8883
    edge = "press-line-1"              # default: the host name
    prefix = "pyrtu"
    qos = 1
    username = "edge1"
    password_file = "/etc/pyrtu/mqtt.pass"
    outbox = "/var/lib/pyrtu/outbox"   # default: outbox-{edge} next to the file

    [[point]]
    name = "weg.reference"
    bus = "line1"
    slave = 1
    table = "holding"
    address = 683
    writable = true
    min = 0
    max = 8192
    max_age = 60                       # republish an unchanged value after 60 s

Per-point keys (also in ``[defaults]``, but ``topic``): ``topic`` (the point's topic
instead of ``{prefix}/{edge}/{bus}/{slave}/{point}``) and ``max_age``; ``writable``,
``min``, ``max`` (what a set command may write), ``deadband`` and the Home Assistant
hints are the poller's point keys (`pyrtu.poller.Point`); ``[defaults]``'
``writable``, ``min`` and ``max`` apply to the points of ``[[device]]`` profiles too.
The ``[mqtt]`` keys are the fields of `MqttConfig`.

Errors are `pyrtu.poller.ConfigError` (a ValueError) naming the file, the line and
the key, like the poller's: ``bridge.toml:4: mqtt: qos: must be 0, 1 or 2, not 3``.
"""

from __future__ import annotations

import json
import math
import os
import socket
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from ..core._tomlpos import locate
from ..core.timing import check_seconds
from ..poller import ConfigError, PollerConfig
from ..poller.config import _Loader, _locate, read_config_text
from .topics import Topics, topic_problem

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: the per-point keys the bridge adds to ``[[point]]`` tables
POINT_KEYS = ("topic", "max_age")
#: the poller's point keys that ``[defaults]`` gives the profiles' points too
PROFILE_DEFAULTS = ("writable", "min", "max")


#: the forms of the JSON bridge's value messages (``[mqtt]`` ``messages``): a message
#: per point update, or one per device per poll
MESSAGES = ("point", "device")


def _real(v: object) -> bool:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)


def _count(key: str, v: object, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"{key}: must be an integer {lo}..{hi}, not {v!r}")
    return v


def _level(key: str, v: object, *, slashes: bool = False) -> str:
    """A topic level (or, with ``slashes``, levels): `topic_problem`."""
    problem = topic_problem(v, levels=slashes)
    if problem is not None:
        raise ValueError(f"{key}: {problem}")
    assert isinstance(v, str)
    return v


@dataclass(frozen=True)
class MqttConfig:
    """The ``[mqtt]`` table: the broker, the topics and the bridge's bounds.

    ``url``: ``mqtt://host[:port]`` (1883) or ``mqtts://host[:port]`` (8883);
    ``password`` or ``password_file`` (its first line); ``ca``/``cert``/``key``
    (PEM files; mqtts only: the CA that signs the broker's certificate, default the
    system's, and a client certificate); ``outbox`` (the directory of the durable
    log); ``fsync_interval`` (seconds between fsync batches); ``command_expiry``
    (seconds a set command without an MQTT 5 expiry stays valid); ``write_rate``
    (writes per second per slave); ``command_queue`` (commands waiting, all
    slaves); ``inflight`` (publications awaiting the broker's acknowledgement);
    ``discovery`` (Home Assistant MQTT discovery under ``discovery_prefix``);
    ``messages`` (``point``: a retained message per point update; ``device``: one
    message per device per poll, ``{prefix}/{edge}/{bus}/{slave}/values``, not
    retained: docs/BRIDGE.md, "Device messages").
    """

    url: str
    edge: str = ""
    prefix: str = "pyrtu"
    client_id: str = ""
    username: str | None = None
    password: str | None = field(default=None, repr=False)
    password_file: str | None = None
    ca: str | None = None
    cert: str | None = None
    key: str | None = None
    keepalive: int = 30
    qos: int = 1
    outbox: str = ""
    outbox_max_bytes: int = 256 * 1024 * 1024
    outbox_policy: str = "drop-oldest"
    fsync_interval: float = 0.05
    stats_interval: float = 5.0
    max_age: float = 0.0
    command_expiry: float = 5.0
    write_rate: float = 20.0
    command_queue: int = 256
    max_payload: int = 1024
    inflight: int = 1000
    backoff: float = 0.5
    max_backoff: float = 30.0
    discovery: bool = False
    discovery_prefix: str = "homeassistant"
    messages: str = "point"

    def __post_init__(self) -> None:
        u = urlsplit(self.url) if isinstance(self.url, str) else None
        if u is None or u.scheme not in ("mqtt", "mqtts") or not u.hostname:
            raise ValueError(
                f"url: must be mqtt://host[:port] or mqtts://host[:port], not {self.url!r}"
            )
        try:
            u.port  # noqa: B018 - raises on a bad port
        except ValueError:
            raise ValueError(f"url: bad port in {self.url!r}") from None
        if u.path not in ("", "/") or u.query or u.username or u.password:
            raise ValueError(
                f"url: only scheme, host and port, not {self.url!r} "
                "(user and password have their own keys)"
            )
        edge = self.edge or _level("edge", socket.gethostname().split(".")[0] or "edge")
        object.__setattr__(self, "edge", _level("edge", edge))
        _level("prefix", self.prefix, slashes=True)
        _level("discovery_prefix", self.discovery_prefix, slashes=True)
        if not isinstance(self.client_id, str):
            raise ValueError(f"client_id: must be a string, not {self.client_id!r}")
        object.__setattr__(self, "client_id", self.client_id or f"pyrtu-bridge-{self.edge}")
        for k in ("username", "password", "password_file", "ca", "cert", "key"):
            v = getattr(self, k)
            if v is not None and (not isinstance(v, str) or (not v and k != "password")):
                raise ValueError(f"{k}: must be a non-empty string, not a {type(v).__name__}")
        if self.password is not None and self.password_file is not None:
            raise ValueError("password_file: give password or password_file, not both")
        if (self.password is not None or self.password_file) and self.username is None:
            raise ValueError("username: a password needs a username")
        if not self.tls and (self.ca or self.cert or self.key):
            k = "ca" if self.ca else "cert" if self.cert else "key"
            raise ValueError(f"{k}: TLS files need an mqtts:// url")
        if bool(self.cert) != bool(self.key):
            raise ValueError(f"{'key' if self.cert else 'cert'}: cert and key go together")
        _count("keepalive", self.keepalive, 5, 65535)
        _count("qos", self.qos, 0, 2)
        if not isinstance(self.outbox, str):
            raise ValueError(f"outbox: must be a directory path, not {self.outbox!r}")
        _count("outbox_max_bytes", self.outbox_max_bytes, 1 << 16, 1 << 50)
        if self.outbox_policy not in ("drop-oldest", "refuse"):
            raise ValueError(
                f"outbox_policy: must be drop-oldest or refuse, not {self.outbox_policy!r}"
            )
        check_seconds("fsync_interval:", self.fsync_interval)  # (the key and its colon)
        check_seconds("stats_interval:", self.stats_interval, True)
        check_seconds("max_age:", self.max_age)
        check_seconds("command_expiry:", self.command_expiry, True)
        if not _real(self.write_rate) or self.write_rate <= 0:
            raise ValueError(f"write_rate: must be a positive number, not {self.write_rate!r}")
        _count("command_queue", self.command_queue, 1, 1 << 20)
        _count("max_payload", self.max_payload, 16, 1 << 20)
        _count("inflight", self.inflight, 1, 65535)
        check_seconds("backoff:", self.backoff, True)
        if not _real(self.max_backoff) or self.max_backoff < self.backoff:
            raise ValueError(f"max_backoff: must be at least backoff, not {self.max_backoff!r}")
        if not isinstance(self.discovery, bool):
            raise ValueError(f"discovery: must be true or false, not {self.discovery!r}")
        if self.messages not in MESSAGES:
            raise ValueError(
                f"messages: must be {' or '.join(map(repr, MESSAGES))}, not {self.messages!r}"
            )
        if self.messages == "device" and self.discovery:
            raise ValueError(
                "messages: 'device' with discovery: Home Assistant reads each point's "
                "retained value on its own topic (messages = 'point')"
            )

    @property
    def tls(self) -> bool:
        return self.url.startswith("mqtts:")

    @property
    def host(self) -> str:
        return urlsplit(self.url).hostname or ""

    @property
    def port(self) -> int:
        return urlsplit(self.url).port or (8883 if self.tls else 1883)

    @property
    def broker(self) -> str:
        """``host:port``, for messages."""
        return f"{self.host}:{self.port}"

    def secret(self) -> str | None:
        """The password (read from ``password_file`` when given); OSError if unreadable."""
        if self.password_file is None:
            return self.password
        text = Path(self.password_file).read_text(encoding="utf-8")
        return text.splitlines()[0] if text else ""


MQTT_KEYS = tuple(f.name for f in fields(MqttConfig))


@dataclass(frozen=True)
class PointOptions:
    """A point's bridge keys: its topic override and the age after which an
    unchanged value is published again (writability and bounds are the point's:
    `pyrtu.poller.Point`)."""

    topic: str | None = None
    max_age: float | None = None

    def __post_init__(self) -> None:
        if self.topic is not None:
            _level("topic", self.topic, slashes=True)
        if self.max_age is not None:
            check_seconds("max_age:", self.max_age)


@dataclass(frozen=True)
class BridgeConfig:
    """The poller's configuration, the broker's and the per-point options."""

    poller: PollerConfig
    mqtt: MqttConfig
    options: Mapping[str, PointOptions] = field(default_factory=dict)
    source: str = "<config>"
    #: (bus, slave) -> (template, name) of the ``[[device]]`` tables with a template
    drives: Mapping[tuple[str, int], tuple[str, str]] = field(default_factory=dict)
    #: the ``[sparkplug]`` table as written (None: none; the JSON mode), read by
    #: `pyrtu.sparkplug.config`
    sparkplug: Mapping[str, Any] | None = None

    def option(self, name: str) -> PointOptions:
        return self.options.get(name) or _NO_OPTIONS

    def max_age(self, name: str) -> float:
        o = self.option(name).max_age
        return self.mqtt.max_age if o is None else o


_NO_OPTIONS = PointOptions()


def _where(text: str, source: str, table: str, key: str | None) -> str:
    """``source:line`` of ``key`` in the single table ``[table]`` (or its header)."""
    line = locate(text, table, key)
    return source if line is None else f"{source}:{line}"


def _error(where: str, label: str, msg: str) -> ConfigError:
    return ConfigError(f"{where}: {label}: {msg}")


#: the ``[mqtt]`` keys that name a file the bridge reads when it starts
FILE_KEYS = ("password_file", "ca", "cert", "key")


def _check_files(mqtt: MqttConfig) -> None:
    """ValueError ``"key: ..."`` for a file key naming no readable regular file."""
    for k in FILE_KEYS:
        name = getattr(mqtt, k)
        if not name:
            continue
        path = Path(name)
        if not path.exists():
            raise ValueError(f"{k}: {name}: no such file")
        if not path.is_file():
            raise ValueError(f"{k}: {name}: not a regular file")
        if not os.access(path, os.R_OK):
            raise ValueError(f"{k}: {name}: not readable (permission denied)")


def _quoted(name: str) -> str:
    """A name in double quotes, its control characters escaped (as JSON does)."""
    return json.dumps(name, ensure_ascii=False)


def _check_levels(
    text: str,
    source: str,
    poller: PollerConfig,
    options: Mapping[str, PointOptions],
    n_profile: int,
    devices: list[Any],
) -> None:
    """Every name that becomes a topic level is one (`topic_problem`): the buses',
    the points' without a ``topic``, the devices' (their profile points' names
    begin with it); ConfigError at the line of the name."""
    for i, b in enumerate(poller.buses):
        problem = topic_problem(b.name)
        if problem is not None:
            line = _locate(text, "bus", i, "name")
            raise ConfigError(f"{source}:{line}: bus[{i}] ({_quoted(b.name)}): name: {problem}")
    for n, p in enumerate(poller.points):
        if options.get(p.name, _NO_OPTIONS).topic is not None:
            continue  # the name is in no topic
        problem = topic_problem(p.name)
        if problem is None:
            continue
        if n >= n_profile:
            i = n - n_profile
            line = _locate(text, "point", i, "name")
            raise ConfigError(
                f"{source}:{line}: point[{i}] ({_quoted(p.name)}): name: {problem} "
                "(a point's name is one level of its topic; or give the point a topic)"
            )
        for j, t in enumerate(devices):
            if isinstance(t, dict) and (t.get("bus"), t.get("slave")) == (p.bus, p.slave):
                line = _locate(text, "device", j, "name")
                own = topic_problem(t["name"]) if "name" in t else None
                raise ConfigError(
                    f"{source}:{line}: device[{j}]: name: {own or problem} "
                    "(the names of its points begin with it: each is one level of a topic)"
                )
        raise ConfigError(f"{source}: point {p.name!r}: name: {problem}")  # pragma: no cover


def _template_keys(poller: PollerConfig, name: str) -> frozenset[str]:
    """The keys the template of a ``[[device]]`` gives its point ``name`` itself (they
    win over ``[defaults]``); none for a profile's or a ``[[point]]``'s point."""
    for device in poller.devices:
        if device.template is None:
            continue
        for raw in device.template.points:
            if f"{device.name}.{raw.get('name')}" == name:
                return frozenset(raw)
    return frozenset()


def _profile_defaults(
    poller: PollerConfig, n_profile: int, defaults: object, text: str, source: str
) -> PollerConfig:
    """The profiles' points with ``[defaults]``' `PROFILE_DEFAULTS` (the ``[[point]]``
    tables have them from the poller's loader; a template's own keys win)."""
    if not isinstance(defaults, Mapping):
        return poller
    given = {k: defaults[k] for k in PROFILE_DEFAULTS if k in defaults}
    if not given or n_profile == 0:
        return poller
    points = list(poller.points)
    for n in range(n_profile):
        own = _template_keys(poller, points[n].name)
        wanted = {k: v for k, v in given.items() if k not in own}
        if not wanted:
            continue
        try:
            points[n] = replace(points[n], **wanted)
        except ValueError as e:  # a default that does not fit a profile point
            line = _where(text, source, "defaults", next(iter(given)))
            raise ConfigError(f"{line}: point {points[n].name!r}: {e} (from [defaults])") from None
    return replace(poller, points=tuple(points))


def parse_bridge_config(
    text: str, source: str = "<config>", base: Path | None = None
) -> BridgeConfig:
    """A bridge configuration from TOML text (``base``: the directory relative
    paths are taken from)."""
    try:
        doc: dict[str, Any] = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: {e}") from None
    mqtt_t = doc.pop("mqtt", None)
    sparkplug_t = doc.pop("sparkplug", None)
    if sparkplug_t is not None and not isinstance(sparkplug_t, Mapping):
        raise ConfigError(f"{source}: sparkplug must be a table ([sparkplug])")
    if not isinstance(mqtt_t, Mapping):
        raise ConfigError(f'{source}: no [mqtt] table (the broker: url = "mqtt://host")')
    for k in mqtt_t:
        if k not in MQTT_KEYS:
            raise _error(
                _where(text, source, "mqtt", k),
                "mqtt",
                f"{k}: unknown key (known: {', '.join(MQTT_KEYS)})",
            )
    if "url" not in mqtt_t:
        raise _error(_where(text, source, "mqtt", None), "mqtt", "url: missing")
    kw = dict(mqtt_t)
    for k in ("password_file", "ca", "cert", "key", "outbox"):
        if isinstance(kw.get(k), str) and kw[k] and base is not None:
            kw[k] = str(base / kw[k])
    try:
        mqtt = MqttConfig(**kw)
        _check_files(mqtt)
    except ValueError as e:
        key = str(e).partition(": ")[0]
        raise _error(
            _where(text, source, "mqtt", key if key in MQTT_KEYS else None), "mqtt", str(e)
        ) from None
    if not mqtt.outbox:
        d = base if base is not None else Path.cwd()
        object.__setattr__(mqtt, "outbox", str(d / f"outbox-{mqtt.edge}"))
    defaults = doc.get("defaults")
    dflt: dict[str, Any] = {}
    if isinstance(defaults, dict):
        for k in POINT_KEYS:
            if k in defaults:
                if k == "topic":
                    raise _error(
                        _where(text, source, "defaults", k),
                        "defaults",
                        "topic: a topic is one point's; not a default",
                    )
                dflt[k] = defaults.pop(k)
    raw_points = doc.get("point", [])
    picked: list[tuple[int, dict[str, Any]]] = []
    if isinstance(raw_points, list):
        for i, t in enumerate(raw_points):
            if isinstance(t, dict):
                picked.append((i, {k: t.pop(k) for k in POINT_KEYS if k in t}))
    default_keys = tuple(k for k in POINT_KEYS if k != "topic")
    poller = _Loader(text, source, POINT_KEYS, default_keys, base=base).load(doc)
    drives = {
        (d.bus, d.slave): (d.template.name, d.name)
        for d in poller.devices
        if d.template is not None
    }
    n_profile = len(poller.points) - len(raw_points if isinstance(raw_points, list) else [])
    options: dict[str, PointOptions] = {}
    if dflt:
        try:
            base_opts = PointOptions(**dflt)
        except ValueError as e:
            key = str(e).partition(": ")[0]
            raise _error(_where(text, source, "defaults", key), "defaults", str(e)) from None
        for p in poller.points:
            options[p.name] = base_opts
    for i, own in picked:
        point = poller.points[n_profile + i]
        label = f'point[{i}] ("{point.name}")'
        try:
            opts = PointOptions(**{**dflt, **own})
        except ValueError as e:
            key = str(e).partition(": ")[0]
            line = _locate(text, "point", i, key if key in own else None)
            note = " (from [defaults])" if key not in own and key in dflt else ""
            raise ConfigError(f"{source}:{line}: {label}: {e}{note}") from None
        options[point.name] = opts
    poller = _profile_defaults(poller, n_profile, defaults, text, source)
    raw_devices = doc.get("device")
    devices: list[Any] = raw_devices if isinstance(raw_devices, list) else []
    _check_levels(text, source, poller, options, n_profile, devices)
    if sparkplug_t is not None and mqtt.messages != "point":
        raise _error(
            _where(text, source, "mqtt", "messages"),
            "mqtt",
            f"messages: {mqtt.messages!r} is the JSON bridge's; a [sparkplug] edge node "
            "publishes a device's changes in one DDATA already (leave messages out)",
        )
    cfg = BridgeConfig(poller, mqtt, options, source, drives, sparkplug_t)
    try:  # the topics must be distinct and valid
        Topics(cfg)
    except ValueError as e:
        if str(e).startswith("messages: "):  # a device messages' topic taken
            raise _error(
                _where(text, source, "mqtt", "messages"),
                "mqtt",
                f"{e} (rename that point, or give it a topic of its own)",
            ) from None
        raise ConfigError(f"{source}: {e}") from None
    return cfg


def load_bridge_config(path: str | Path) -> BridgeConfig:
    """A bridge configuration from a TOML file; `ConfigError` names the file, the
    line and the key on any problem.  Nothing is opened (no port, no broker)."""
    p = Path(path)
    return parse_bridge_config(read_config_text(p), p.name or str(p), p.resolve().parent)


def make_bridge_config(
    poller: PollerConfig, mqtt: MqttConfig, options: Mapping[str, PointOptions] | None = None
) -> BridgeConfig:
    """A checked configuration from Python objects (ConfigError on a mismatch)."""
    opts = dict(options or {})
    try:
        _check_files(mqtt)
    except ValueError as e:
        raise ConfigError(f"mqtt: {e}") from None
    names = {p.name: p for p in poller.points}
    for n in opts:
        if n not in names:
            raise ConfigError(f"options: no point named {n!r}")
    if not mqtt.outbox:
        object.__setattr__(mqtt, "outbox", str(Path.cwd() / f"outbox-{mqtt.edge}"))
    cfg = BridgeConfig(poller, mqtt, opts, "<python>")
    try:
        Topics(cfg)
    except ValueError as e:
        raise ConfigError(f"<python>: {e}") from None
    return cfg


__all__ = [
    "FILE_KEYS",
    "MESSAGES",
    "MQTT_KEYS",
    "POINT_KEYS",
    "BridgeConfig",
    "MqttConfig",
    "PointOptions",
    "load_bridge_config",
    "make_bridge_config",
    "parse_bridge_config",
]
