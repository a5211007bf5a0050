"""Whether two port names are the same port, for refusing one port given twice.

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

import os
from collections.abc import Iterable

__all__ = ["first_duplicate", "port_key", "same_port"]


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
