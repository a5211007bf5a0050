"""Deprecated path: this module lives in `pyrtu.outbox._format` (the northbound-neutral
outbox, shared by every output).  Each name used here warns (`DeprecationWarning`)
naming its new path."""

from __future__ import annotations

from pyrtu.core._deprecated import moved

__getattr__ = moved(
    __name__,
    "pyrtu.outbox._format",
    [
        "CRC",
        "CursorState",
        "FORMAT_VERSION",
        "Item",
        "MAX_SEQ",
        "REC_HEAD",
        "REC_MAGIC",
        "REC_PRE",
        "SEGMENT_NAME",
        "SEG_HEAD",
        "SEG_MAGIC",
        "STATE",
        "STATE_MAGIC",
        "STATE_SIZE",
        "STATE_SLOTS",
        "cursor_version",
        "decode_state",
        "encode_record",
        "encode_state",
        "parse_segment_header",
        "scan",
        "segment_header",
        "segment_name",
        "segment_version",
    ],
)
