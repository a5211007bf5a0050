"""Home Assistant MQTT discovery (``discovery = true``): one retained config per
point under ``{discovery_prefix}/{component}/pyrtu_{edge}/{object}/config``.

Points are grouped into one Home Assistant device per device (bus and slave): its
manufacturer, model and name come from the ``[[device]]`` table's template (its
``vendor`` and ``model``) and ``name`` (``cfw701`` -> "WEG", "CFW701"), else
"Modbus slave N on BUS"; a template point's ``unit``, ``device_class``,
``state_class``, ``icon`` and ``precision`` become the entity's
``unit_of_measurement``, ``device_class``, ``state_class``, ``icon`` and
``suggested_display_precision``.  Read-only points are
``sensor`` (``binary_sensor`` for bits), writable ones ``number`` (with ``min``,
``max`` and the step of the point's scale), ``switch`` for bits, ``text`` for
strings and ``select`` for enumerations (a read-only one is a ``sensor`` of device
class ``enum`` with its labels as options), their command topic the point's set
topic.  A point's ``unit``, ``precision``, ``device_class``, ``state_class`` and
``icon`` become ``unit_of_measurement``, ``suggested_display_precision`` (sensors;
a number's step), ``device_class``, ``state_class`` and ``icon``.  Availability is the edge's
status and the slave's, both ``online``: a drive that stops answering, or an edge
that is gone, shows unavailable.  Pure: `configs` returns (topic, payload) pairs.
"""

from __future__ import annotations

import json
import re
from typing import TYPE_CHECKING, Any

from ..pdu.codecs import CODECS, FLOAT_MAX
from ..poller import Point

if TYPE_CHECKING:
    from .config import BridgeConfig
    from .topics import Topics


def _id(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)


def component(point: Point, writable: bool) -> str:
    if point.labels:
        return "select" if writable else "sensor"
    if point.type == "bool":
        return "switch" if writable else "binary_sensor"
    if point.type in ("string", "string1"):
        return "text" if writable else "sensor"
    return "number" if writable else "sensor"


def configs(cfg: BridgeConfig, topics: Topics) -> list[tuple[str, bytes]]:
    """The retained discovery messages of every point (topic, JSON payload)."""
    m = cfg.mqtt
    node = _id(f"pyrtu_{m.edge}")
    out: list[tuple[str, bytes]] = []
    devices = {(d.bus, d.slave): d for d in cfg.poller.devices if d.template is not None}
    for p in cfg.poller.points:
        kind = component(p, p.writable)
        known = devices.get((p.bus, p.slave))
        template = known.template if known is not None else None
        dev_name = known.name if known is not None else None
        maker = template.vendor if template is not None else None
        model = template.model if template is not None else "Modbus slave"
        device: dict[str, Any] = {
            "identifiers": [_id(f"pyrtu_{m.edge}_{p.bus}_{p.slave}")],
            "name": dev_name or f"{model} {p.slave} on {p.bus}",
            "model": model,
            "via_device": node,
        }
        if maker:
            device["manufacturer"] = maker
        label = (
            p.name[len(dev_name) + 1 :]
            if dev_name and p.name.startswith(dev_name + ".")
            else p.name
        )
        doc: dict[str, Any] = {
            "name": label,
            "unique_id": _id(f"pyrtu_{m.edge}_{p.bus}_{p.slave}_{p.name}"),
            "state_topic": topics.point[p.name],
            "availability": [
                {"topic": topics.edge_status},
                {"topic": topics.slave_status[(p.bus, p.slave)]},
            ],
            "availability_mode": "all",
            "payload_available": "online",
            "payload_not_available": "offline",
            "device": device,
        }
        if p.type == "bool" and not p.labels:
            doc["value_template"] = "{{ 'ON' if value_json.value else 'OFF' }}"
        else:
            doc["value_template"] = "{{ value_json.value }}"
        _hints(p, kind, doc)
        if p.writable:
            doc["command_topic"] = topics.point[p.name] + "/set"
            if kind == "switch":
                doc.update(payload_on="true", payload_off="false", state_on="ON", state_off="OFF")
            elif kind == "select":
                doc["options"] = list(p.labels)
                doc["command_template"] = "{{ value | tojson }}"
            elif kind == "text":
                doc["command_template"] = "{{ value | tojson }}"
                doc["max"] = (1 if p.type == "string1" else 2) * p.count
            else:
                doc["command_template"] = "{{ value }}"
                doc["min"] = p.min if p.min is not None else _raw_bound(p, low=True)
                doc["max"] = p.max if p.max is not None else _raw_bound(p, low=False)
                if CODECS[p.type].kind == "float":
                    step = 10.0**-p.precision if p.precision is not None else 0.001
                else:
                    step = abs(p.scale)
                doc["step"] = step
                doc["mode"] = "box"
        topic = f"{m.discovery_prefix}/{kind}/{node}/{_id(f'{p.bus}_{p.slave}_{p.name}')}/config"
        out.append((topic, json.dumps(doc, separators=(",", ":")).encode()))
    return out


def _hints(p: Point, kind: str, doc: dict[str, Any]) -> None:
    """The point's Home Assistant hints (its unit, precision, classes, icon)."""
    if p.unit:
        doc["unit_of_measurement"] = p.unit
    if p.device_class:
        doc["device_class"] = p.device_class
    elif kind == "sensor" and p.labels:
        doc["device_class"] = "enum"
    if kind == "sensor" and p.labels:
        doc["options"] = list(p.labels)
    if p.state_class and kind == "sensor":
        doc["state_class"] = p.state_class
    if p.icon:
        doc["icon"] = p.icon
    if p.precision is not None and kind == "sensor":
        doc["suggested_display_precision"] = p.precision


def _raw_bound(p: Point, low: bool) -> float:
    codec = CODECS[p.type]
    if codec.kind == "float":
        lo, hi = -FLOAT_MAX[p.type], FLOAT_MAX[p.type]
    elif p.bits is not None:
        width = p.bits[1]
        lo, hi = (
            (-(1 << (width - 1)), (1 << (width - 1)) - 1)
            if p.type == "int16"
            else (0, (1 << width) - 1)
        )
    else:
        lo, hi = codec.low, codec.high
    a, b = lo * p.scale + p.offset, hi * p.scale + p.offset
    return min(a, b) if low else max(a, b)


__all__ = ["component", "configs"]
