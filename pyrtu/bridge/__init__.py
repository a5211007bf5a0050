"""``pyrtu bridge``: the poller's points to an MQTT broker and set commands back.

============  =====================================================================
`config`      `MqttConfig`, `PointOptions`, `BridgeConfig`; `load_bridge_config`
`topics`      topic names, the payload of a value made from a point update
`report`      `Reporter`: report by exception, qualities (good, stale, bad)
`commands`    set commands: parsing, checks, expiry, idempotence, rate limits
`delivery`    `DeliveryWindow`: publications awaiting the broker's acknowledgement
`outbox`      `Outbox`: the durable, bounded on-disk log between poller and broker
`mqtt`        `MqttLink`: one MQTT 5 connection (paho-mqtt) on the asyncio loop
`writes`      `SetWriter`: commands to the drives, read-back, results
`output`      `MqttOutput`: what the JSON bridge and the Sparkplug edge node share
`bridge`      `Bridge`: all of it on the poller
`discovery`   Home Assistant MQTT discovery
============  =====================================================================

See ``docs/BRIDGE.md``.  The MQTT client is paho-mqtt (``pip install pyrtu[bridge]``).
"""

from __future__ import annotations

from pyrtu.core._lazy import lazy_attributes

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


#: ``Bridge`` and ``BridgeEvent`` (the driver needs paho-mqtt; the configuration, for
#: ``pyrtu bridge --check``, does not) and the submodules, on first use
__getattr__ = lazy_attributes(
    __name__, {"Bridge": "pyrtu.bridge.bridge", "BridgeEvent": "pyrtu.bridge.bridge"}
)
