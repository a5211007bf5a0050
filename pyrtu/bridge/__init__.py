"""``pyrtu bridge``: the poller's points to an MQTT broker and set commands back.

============  =====================================================================
`config`      `MqttConfig`, `PointOptions`, `BridgeConfig`; `load_bridge_config`
`topics`      topic names, the payload of a value, outbox records
`report`      `Reporter`: report by exception, qualities (good, stale, bad)
`commands`    set commands: parsing, checks, expiry, idempotence, rate limits
`delivery`    `DeliveryWindow`: publications awaiting the broker's acknowledgement
`outbox`      `Outbox`: the durable, bounded on-disk log between poller and broker
`mqtt`        `MqttLink`: one MQTT 5 connection (paho-mqtt) on the asyncio loop
`writes`      `SetWriter`: commands to the drives, read-back, results
`bridge`      `Bridge`: all of it on the poller
`discovery`   Home Assistant MQTT discovery
============  =====================================================================

See ``docs/BRIDGE.md``.  The MQTT client is paho-mqtt (``pip install pyrtu[bridge]``).
"""

from __future__ import annotations

from .config import (
    BridgeConfig,
    MqttConfig,
    PointOptions,
    load_bridge_config,
    make_bridge_config,
    parse_bridge_config,
)

__all__ = [
    "Bridge",
    "BridgeConfig",
    "BridgeEvent",
    "MqttConfig",
    "PointOptions",
    "load_bridge_config",
    "make_bridge_config",
    "parse_bridge_config",
]


def __getattr__(name: str) -> object:
    # the driver needs paho-mqtt; the configuration (pyrtu bridge --check) does not
    if name in ("Bridge", "BridgeEvent"):
        from . import bridge

        return getattr(bridge, name)
    raise AttributeError(f"module 'pyrtu.bridge' has no attribute {name!r}")
