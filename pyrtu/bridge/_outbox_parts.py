"""Deprecated path: this module lives in `pyrtu.outbox._parts` (the northbound-neutral
outbox, shared by every output).  Each name used here warns (`DeprecationWarning`)
naming its new path."""

from __future__ import annotations

from pyrtu.core._deprecated import moved

__getattr__ = moved(
    __name__,
    "pyrtu.outbox._parts",
    [
        "INDEX_STRIDE",
        "OutboxError",
        "OutboxFull",
        "OutboxLimits",
        "RESERVE",
        "Segment",
        "WRITE_CHUNK",
        "active_reader",
        "check_int",
        "error",
        "io_error",
        "lock_directory",
        "recover_segment",
    ],
)
