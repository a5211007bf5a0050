"""The ``[sparkplug]`` table: `pyrtu bridge` as a Sparkplug B 3.0 edge node.

::

    [mqtt]                      # the broker, shared: url, credentials, TLS, outbox...
    url = "mqtt://broker"
    edge = "press-line"

    [sparkplug]
    group_id = "plant1"          # required
    edge_node_id = "press-line"  # default: [mqtt] edge
    primary_host_id = "scada"    # optional: publish only while it is online
    bdseq_file = "bdseq"         # default: the outbox's path + ".bdseq"

The devices are the poller's (one Sparkplug device per bus and slave: the
``[[device]]``'s ``name``, else ``{bus}-{slave}``).  Errors name the file, the line
and the key (`ConfigError`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..bridge.config import BridgeConfig, _where, load_bridge_config
from ..poller import ConfigError
from ..poller.config import read_config_text
from .metrics import DeviceDef, check_id, devices

KEYS = ("group_id", "edge_node_id", "primary_host_id", "bdseq_file")
#: the node's own metrics take the first aliases: bdSeq 1 (Node Control/Rebirth has
#: none: tck-id-operational-behavior-data-commands-rebirth-name-aliases; 2 is kept)
NODE_ALIASES = {"bdSeq": 1, "Node Control/Rebirth": 2}


@dataclass(frozen=True)
class SparkplugConfig:
    """The bridge's configuration and the edge node's identity (see the module doc)."""

    bridge: BridgeConfig
    group_id: str
    edge_node_id: str
    primary_host_id: str | None
    bdseq_file: str
    devices: tuple[DeviceDef, ...]


def sparkplug_config(
    bridge: BridgeConfig, table: Mapping[str, Any], text: str = "", base: Path | None = None
) -> SparkplugConfig:
    """The edge node's configuration from a `BridgeConfig` and its ``[sparkplug]``
    table (``text``: the TOML, for the lines of errors)."""
    source = bridge.source

    def fail(key: str | None, message: str) -> ConfigError:
        where = _where(text, source, "sparkplug", key) if text else source
        return ConfigError(f"{where}: sparkplug: {message}")

    for k in table:
        if k not in KEYS:
            raise fail(k, f"{k}: unknown key (known: {', '.join(KEYS)})")
    if "group_id" not in table:
        raise fail(None, 'group_id: missing (the Sparkplug group: group_id = "plant1")')
    ids: dict[str, str | None] = {}
    for k, default in (
        ("group_id", None),
        ("edge_node_id", bridge.mqtt.edge),
        ("primary_host_id", None),
    ):
        value = table.get(k, default)
        if value is None:
            ids[k] = None
            continue
        try:
            ids[k] = check_id(k, value)
        except ValueError as e:
            raise fail(k, str(e)) from None
    bdseq = table.get("bdseq_file", "")
    if not isinstance(bdseq, str):
        raise fail("bdseq_file", "bdseq_file must be a path (a string)")
    if not bdseq:
        bdseq = bridge.mqtt.outbox + ".bdseq"
    elif base is not None:
        bdseq = str(base / bdseq)
    names = {(d.bus, d.slave): d.name for d in bridge.poller.devices if d.name}
    try:
        devs = devices(bridge.poller.points, names, first_alias=len(NODE_ALIASES) + 1)
    except ValueError as e:
        raise fail(None, str(e)) from None
    templates = {(d.bus, d.slave): d.template.name for d in bridge.poller.devices if d.template}
    devs = tuple(
        DeviceDef(d.id, d.bus, d.slave, d.metrics, templates.get((d.bus, d.slave), ""))
        for d in devs
    )
    group, edge = ids["group_id"], ids["edge_node_id"]
    assert group is not None and edge is not None
    return SparkplugConfig(bridge, group, edge, ids["primary_host_id"], bdseq, devs)


def load_sparkplug_config(path: str | Path) -> SparkplugConfig:
    """The edge node's configuration from a TOML file with a ``[sparkplug]`` table;
    `ConfigError` names the file, the line and the key.  Nothing is opened."""
    p = Path(path)
    bridge = load_bridge_config(p)
    if bridge.sparkplug is None:
        raise ConfigError(f"{p.name or p}: no [sparkplug] table")
    return sparkplug_config(bridge, bridge.sparkplug, read_config_text(p), p.resolve().parent)


__all__ = ["KEYS", "NODE_ALIASES", "SparkplugConfig", "load_sparkplug_config", "sparkplug_config"]
