"""The outbox's quarantine: records that can never be published, moved aside.

A record that cannot be published (one of a point the output does not have, an
earlier record whose topic no broker accepts: a wildcard, NUL or control
character, or one the MQTT client or the broker refuses) would otherwise stay
first in line for ever, blocking every record behind it.  `Quarantine.add` copies
it, one JSON line per record, to ``quarantine.jsonl`` in the outbox's directory::

    {"seq": 17, "time": 1732550400.1, "reason": "...", "record": "\\u0000pu1[...]"}

(``record``: the record as text, a point update or an earlier pyrtu's topic and
payload, or ``record_base64`` when it is not UTF-8); the caller then passes it by
as if delivered.  `sync` makes the lines durable; the outbox calls it before its
ack cursor passes them, so a crash loses none (it may copy a record twice: the
same ``seq``).  The segment files are not changed.
"""

from __future__ import annotations

import base64
import json
import os
import time
from pathlib import Path

from pyrtu.outbox._parts import io_error

#: the file's name in the outbox's directory
QUARANTINE_NAME = "quarantine.jsonl"


class Quarantine:
    """The quarantine file of one outbox directory (opened at the first `add`)."""

    def __init__(self, directory: Path, dir_fd: int) -> None:
        self.directory = directory
        self.path = directory / QUARANTINE_NAME
        self._dir_fd = dir_fd
        self._fd = -1
        self._dirty = False
        self.count = 0  # records added since this object was made

    def add(self, seq: int, record: bytes, reason: str) -> None:
        """Copy a record aside (durable at the next `sync`); OutboxError on a disk error."""
        doc: dict[str, object] = {"seq": seq, "time": round(time.time(), 6), "reason": reason}
        try:
            doc["record"] = record.decode("utf-8")
        except UnicodeDecodeError:
            doc["record_base64"] = base64.b64encode(record).decode("ascii")
        line = (json.dumps(doc, ensure_ascii=False) + "\n").encode("utf-8")
        try:
            if self._fd < 0:
                self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
                os.fsync(self._dir_fd)  # the file's name, in case it is new
            view = memoryview(line)
            while view:
                view = view[os.write(self._fd, view) :]
        except OSError as exc:
            raise io_error(self.directory, "writing", QUARANTINE_NAME, exc) from exc
        self._dirty = True
        self.count += 1

    def sync(self) -> None:
        """Make the lines added so far durable (nothing to do when none)."""
        if not self._dirty:
            return
        try:
            os.fsync(self._fd)
        except OSError as exc:
            raise io_error(self.directory, "fsyncing", QUARANTINE_NAME, exc) from exc
        self._dirty = False

    def close(self) -> None:
        """Sync and close (idempotent)."""
        if self._fd >= 0:
            try:
                self.sync()
            finally:
                os.close(self._fd)
                self._fd = -1


__all__ = ["QUARANTINE_NAME", "Quarantine"]
