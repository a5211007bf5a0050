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
``max`` and the step of the point's scale), ``switch`` for bits and ``text`` for
strings, their command topic the point's set topic.  Availability is the edge's
status and the slave's, both ``online``: a drive that stops answering, or an edge
that is gone, shows unavailable.  Pure: `configs` returns (topic, payload) pairs.
"""

from __future__ import annotations

import json
import re
from typing import TYPE_CHECKING, Any

from ..poller import Point

if TYPE_CHECKING:
    from .config import BridgeConfig
    from .topics import Topics

#: a template point's hints -> Home Assistant's keys
HINTS = {
    "unit": "unit_of_measurement",
    "device_class": "device_class",
    "state_class": "state_class",
    "icon": "icon",
    "precision": "suggested_display_precision",
}


def _id(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)


def component(point: Point, writable: bool) -> str:
    if point.type == "bool":
        return "switch" if writable else "binary_sensor"
    if point.type == "string":
        return "text" if writable else "sensor"
    return "number" if writable else "sensor"


def configs(cfg: BridgeConfig, topics: Topics) -> list[tuple[str, bytes]]:
    """The retained discovery messages of every point (topic, JSON payload)."""
    m = cfg.mqtt
    node = _id(f"pyrtu_{m.edge}")
    out: list[tuple[str, bytes]] = []
    devices = {(d.bus, d.slave): d for d in cfg.poller.devices if d.template is not None}
    for p in cfg.poller.points:
        opts = cfg.option(p.name)
        kind = component(p, opts.writable)
        known = devices.get((p.bus, p.slave))
        template = known.template if known is not None else None
        dev_name = known.name if known is not None else None
        maker = template.vendor if template is not None else None
        model = template.model if template is not None else "Modbus slave"
        hints = known.hints.get(p.name, {}) if known is not None else {}
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
        for key, ha_key in HINTS.items():
            hint = hints.get(key, getattr(p, key, None))
            if hint is not None and not (kind != "sensor" and key == "state_class"):
                doc[ha_key] = hint
        if p.type == "bool":
            doc["value_template"] = "{{ 'ON' if value_json.value else 'OFF' }}"
        else:
            doc["value_template"] = "{{ value_json.value }}"
        if opts.writable:
            doc["command_topic"] = topics.point[p.name] + "/set"
            if kind == "switch":
                doc.update(payload_on="true", payload_off="false", state_on="ON", state_off="OFF")
            elif kind == "text":
                doc["command_template"] = "{{ value | tojson }}"
                doc["max"] = 2 * p.count
            else:
                doc["command_template"] = "{{ value }}"
                doc["min"] = opts.min if opts.min is not None else _raw_bound(p, low=True)
                doc["max"] = opts.max if opts.max is not None else _raw_bound(p, low=False)
                doc["step"] = abs(p.scale) if p.type != "float32" else 0.001
                doc["mode"] = "box"
        topic = f"{m.discovery_prefix}/{kind}/{node}/{_id(f'{p.bus}_{p.slave}_{p.name}')}/config"
        out.append((topic, json.dumps(doc, separators=(",", ":")).encode()))
    return out


def _raw_bound(p: Point, low: bool) -> float:
    lo, hi = {
        "uint16": (0, 0xFFFF),
        "int16": (-0x8000, 0x7FFF),
        "uint32": (0, 2**32 - 1),
        "int32": (-(2**31), 2**31 - 1),
    }.get(p.type, (-3.4e38, 3.4e38))
    a, b = lo * p.scale + p.offset, hi * p.scale + p.offset
    return min(a, b) if low else max(a, b)


__all__ = ["HINTS", "component", "configs"]
