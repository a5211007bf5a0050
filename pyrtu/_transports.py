"""Masters for other transports, by URL scheme: a leaf registry (imports nothing).

``Master("tcp://host:port")`` and ``AsyncMaster(...)`` pick their class here in
``__new__``; `pyrtu._tcp_master` registers the Modbus TCP and RTU-over-TCP classes
(imported by the package), so `master` and `aio` never import the transports that
subclass them.
"""

from __future__ import annotations

from typing import Any

#: scheme -> class, for the sync `Master` ("sync") and `AsyncMaster` ("async")
TRANSPORTS: dict[str, dict[str, type]] = {"sync": {}, "async": {}}


def transport_for(kind: str, port: Any) -> type | None:
    """The registered class for ``port`` (a URL string), or None."""
    if not isinstance(port, str) or "://" not in port:
        return None
    return TRANSPORTS[kind].get(port.split("://", 1)[0].lower())
