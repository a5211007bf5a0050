"""Port names: which URL schemes open, and whether two names are the same port.

A port name with ``://`` is a URL: pyrtu's own ``tcp://`` (Modbus TCP),
``rtu+tcp://`` (RTU frames over TCP), ``mbaps://`` (Modbus TCP in TLS) and ``udp://``
(Modbus over UDP), or one of pyserial's (``socket://``,
``rfc2217://``, ``loop://``...: the handlers pyserial finds).  `url_scheme` says
which, and refuses any other before anything is opened, naming the supported
schemes::

    url_scheme("tcp://plc:502")         # "tcp"
    url_scheme("quic://plc:502")        # ValueError: quic://plc:502: unsupported scheme
                                        # quic://; supported: tcp://, rtu+tcp://, ...

A process that opens one serial port twice gets "busy: another program holds it"
from the exclusive lock at the second open, which blames somebody else for a
usage error.  The commands and the poller's TOML loader compare the names first:

    same_port("/tmp/bus/drop1", "./drop1")          # True when run in /tmp/bus
    first_duplicate(["/dev/ttyUSB0", "/dev/../dev/ttyUSB0"])   # (0, 1)

A file-system path is compared by what it resolves to (``./P``, ``P``, ``a/../P``
and a symlink to ``P`` are one port: the drops of `pyrtu.vbus` are symlinks to
``/dev/pts/N``).  A URL (``socket://``, ``tcp://``, ``loop://``...) is never a
duplicate: each opens a connection of its own, and two ``loop://`` are two
loops.  Any other object (an open serial instance) is the same port only as
itself.
"""

from __future__ import annotations

import importlib
import os
import pkgutil
from collections.abc import Iterable

__all__ = [
    "MBAPS_SCHEME",
    "MBAP_SCHEMES",
    "NETWORK_SCHEMES",
    "RTU_TCP_SCHEME",
    "TCP_SCHEME",
    "UDP_SCHEME",
    "first_duplicate",
    "port_key",
    "same_port",
    "supported_schemes",
    "url_scheme",
]

#: pyrtu's own URL schemes (`pyrtu.drivers.links`): Modbus TCP, RTU frames over TCP,
#: Modbus/TCP Security (Modbus TCP in TLS), Modbus over UDP
TCP_SCHEME = "tcp"
RTU_TCP_SCHEME = "rtu+tcp"
MBAPS_SCHEME = "mbaps"
UDP_SCHEME = "udp"
PYRTU_SCHEMES = (TCP_SCHEME, RTU_TCP_SCHEME, MBAPS_SCHEME, UDP_SCHEME)
#: the schemes of MBAP links (`pyrtu.tcp.link`): plain, or in TLS
MBAP_SCHEMES = (TCP_SCHEME, MBAPS_SCHEME)
#: the schemes of the ports that reach a host over a network: pyrtu's own (each a
#: transport of `pyrtu.drivers.links.TRANSPORTS`) and pyserial's
NETWORK_SCHEMES = frozenset({*PYRTU_SCHEMES, "socket", "rfc2217"})


def url_scheme(port: object, own: tuple[str, ...] = PYRTU_SCHEMES) -> str | None:
    """The scheme of a URL port name, in lower case (``"tcp"``, ``"socket"``...); None
    for a path or an object.  ValueError naming the URL and the supported schemes when
    it is neither one of ``own`` (pyrtu's: `pyrtu.Master` opens them; none for a bare
    serial port, `pyrtu.drivers.port.open_port`) nor one pyserial opens."""
    if not isinstance(port, str) or "://" not in port:
        return None
    scheme = port.split("://", 1)[0].lower()
    if scheme in own or _pyserial_opens(scheme):
        return scheme
    supported = ", ".join(f"{name}://" for name in supported_schemes(own))
    raise ValueError(f"{port}: unsupported scheme {scheme}://; supported: {supported}")


def _pyserial_opens(scheme: str) -> bool:
    """Whether `serial.serial_for_url` finds a handler for ``scheme`` (as it looks)."""
    import serial

    for package in serial.protocol_handler_packages:
        try:
            importlib.import_module(f".protocol_{scheme}", package)
        except (ImportError, ValueError, TypeError):  # (a name no module can have)
            continue
        return True
    return False


def supported_schemes(own: tuple[str, ...] = PYRTU_SCHEMES) -> list[str]:
    """``own``, then the schemes pyserial opens here (its handlers that import)."""
    import serial

    found: set[str] = set()
    for package in serial.protocol_handler_packages:
        try:
            where = importlib.import_module(package).__path__
        except (ImportError, AttributeError):
            continue
        for module in pkgutil.iter_modules(where):
            name = module.name.removeprefix("protocol_")
            if name != module.name and name not in own and _pyserial_opens(name):
                found.add(name)
    return [*own, *sorted(found)]


def port_key(port: object) -> object:
    """What identifies ``port``: the resolved path of a file-system name, None for a
    URL (no duplicate), else the object's identity."""
    if not isinstance(port, str):
        return ("object", id(port))
    if "://" in port or not port:
        return None
    try:
        return os.path.realpath(os.path.expanduser(port))
    except (OSError, ValueError):  # a name with a NUL byte: let the open say what is wrong
        return port


def same_port(a: object, b: object) -> bool:
    """Whether ``a`` and ``b`` name one port."""
    key = port_key(a)
    return key is not None and key == port_key(b)


def first_duplicate(ports: Iterable[object]) -> tuple[int, int] | None:
    """The indexes ``(first, second)`` of the first port named again, or None."""
    seen: dict[object, int] = {}
    for i, port in enumerate(ports):
        key = port_key(port)
        if key is None:
            continue
        if key in seen:
            return seen[key], i
        seen[key] = i
    return None
