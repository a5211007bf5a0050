"""The edge node's Sparkplug session (sans-I/O: time is an input): topics,
sequence numbers, the birth/death sequence number, the payloads of births, deaths
and data, and the primary host's state.

* ``seq`` (0..255, wrapping) numbers every NBIRTH, DBIRTH, NDATA, DDATA and DDEATH
  of the node in one sequence; an NBIRTH starts it again at 0.
* ``bdSeq`` (0..255) is the will's (NDEATH's) and the next NBIRTH's; it increments
  on every connect and is kept on disk (`BdSeqStore`) so that a restarted node
  never reuses the last one.
* Timestamps are UTC milliseconds since the epoch, on every payload and metric.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..poller.points import Value
from .config import NODE_ALIASES, SparkplugConfig
from .metrics import (
    BDSEQ,
    BOOLEAN,
    INT32,
    INT64,
    NODE_REBIRTH,
    QUALITY,
    DeviceDef,
    MetricDef,
    add_property,
    set_value,
)
from .payload import payload_class

NAMESPACE = "spBv1.0"


def millis(t: float) -> int:
    """Unix seconds as the specification's UTC milliseconds."""
    return round(t * 1000)


class BdSeqStore:
    """The next bdSeq, kept in a file (written whole, fsynced, renamed into place)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    def load(self) -> int:
        try:
            text = self.path.read_text(encoding="ascii").strip()
        except FileNotFoundError:
            return 0
        if not text.isdigit() or int(text) > 255:
            raise ValueError(f"{self.path}: not a bdSeq (0..255): {text[:20]!r}")
        return int(text)

    def take(self) -> int:
        """The bdSeq of this connect; the next one saved first (durably)."""
        current = self.load()
        tmp = self.path.with_name(self.path.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            os.write(fd, b"%d\n" % ((current + 1) % 256))
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)
        dfd = os.open(self.path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
        return current


@dataclass(frozen=True, slots=True)
class LatestValue:
    """A metric's value for a message: ``time`` Unix seconds (None: never read)."""

    value: Value | None
    time: float | None
    quality: str = "good"
    historical: bool = False


class EdgeSession:
    """Topics and payloads of one edge node (see the module docstring)."""

    def __init__(self, cfg: SparkplugConfig) -> None:
        self.cfg = cfg
        g, e = cfg.group_id, cfg.edge_node_id
        self.nbirth_topic = f"{NAMESPACE}/{g}/NBIRTH/{e}"
        self.ndeath_topic = f"{NAMESPACE}/{g}/NDEATH/{e}"
        self.ndata_topic = f"{NAMESPACE}/{g}/NDATA/{e}"
        self.ncmd_topic = f"{NAMESPACE}/{g}/NCMD/{e}"
        self.dcmd_filter = f"{NAMESPACE}/{g}/DCMD/{e}/+"
        self.state_topic = (
            None if cfg.primary_host_id is None else f"{NAMESPACE}/STATE/{cfg.primary_host_id}"
        )
        self.device = {d.id: d for d in cfg.devices}
        self.by_slave = {(d.bus, d.slave): d for d in cfg.devices}
        self.metric = {m.point.name: (d, m) for d in cfg.devices for m in d.metrics}
        self._seq = 0
        self.bdseq = 0

    def topic(self, kind: str, device: DeviceDef) -> str:
        return f"{NAMESPACE}/{self.cfg.group_id}/{kind}/{self.cfg.edge_node_id}/{device.id}"

    def next_seq(self) -> int:
        seq = self._seq
        self._seq = (seq + 1) % 256
        return seq

    def _payload(self, now: float, seq: bool = True) -> Any:
        p = payload_class()()
        p.timestamp = millis(now)
        if seq:
            p.seq = self.next_seq()
        return p

    def ndeath(self, bdseq: int, now: float) -> bytes:
        """The NDEATH (the will's payload): bdSeq as an Int64, no seq."""
        p = self._payload(now, seq=False)
        m = p.metrics.add()
        m.name = BDSEQ
        m.timestamp = millis(now)
        m.datatype = INT64
        m.long_value = bdseq
        return bytes(p.SerializeToString())

    def nbirth(self, now: float) -> bytes:
        """The NBIRTH: seq 0, the session's bdSeq, every node metric."""
        self._seq = 0
        p = self._payload(now)
        for name, dtype, value in ((BDSEQ, INT64, self.bdseq), (NODE_REBIRTH, BOOLEAN, False)):
            m = p.metrics.add()
            m.name = name
            if name != NODE_REBIRTH:  # rebirth-name-aliases: the Rebirth metric has none
                m.alias = NODE_ALIASES[name]
            m.timestamp = millis(now)
            m.datatype = dtype
            if dtype == INT64:
                m.long_value = int(value)
            else:
                m.boolean_value = bool(value)
        return bytes(p.SerializeToString())

    def dbirth(self, device: DeviceDef, samples: dict[str, LatestValue], now: float) -> bytes:
        """A DBIRTH: every metric of ``device`` with name, alias, datatype, its
        properties and its current value (``samples``: point name -> value; a
        point never read is null)."""
        p = self._payload(now)
        for md in device.metrics:
            s = samples.get(md.point.name) or LatestValue(None, None, "stale")
            m = p.metrics.add()
            m.name = md.name
            m.alias = md.alias
            m.datatype = md.datatype
            self._fill(m, md, s, now)
            md.birth_properties(m)
            if s.quality != "good":
                add_property(m.properties, "Quality", INT32, QUALITY[s.quality])
        return bytes(p.SerializeToString())

    def ddeath(self, now: float) -> bytes:
        return bytes(self._payload(now).SerializeToString())

    def ddata(self, items: Iterable[tuple[MetricDef, LatestValue]], now: float) -> bytes:
        """A DDATA (or NDATA): each metric by alias only, with its timestamp and
        value; ``is_historical`` for a stored one; ``Quality`` unless good."""
        p = self._payload(now)
        for md, s in items:
            m = p.metrics.add()
            m.alias = md.alias
            self._fill(m, md, s, now)
            if s.historical:
                m.is_historical = True
            if s.quality != "good":
                add_property(m.properties, "Quality", INT32, QUALITY[s.quality])
        return bytes(p.SerializeToString())

    @staticmethod
    def _fill(m: Any, md: MetricDef, s: LatestValue, now: float) -> None:
        m.timestamp = millis(now if s.time is None else s.time)
        value = s.value
        if isinstance(value, float) and not math.isfinite(value) and md.datatype not in (9, 10):
            value = None
        set_value(m, md.datatype, value)


@dataclass(slots=True)
class HostState:
    """The primary host's last STATE (``online``, its ``timestamp``)."""

    online: bool = False
    timestamp: int = -1

    def update(self, payload: bytes) -> bool | None:
        """Take a STATE message: the host's new ``online`` when it is accepted, None
        when it is refused (not the STATE JSON, or a timestamp older than the last
        one accepted: a stale retained or delayed message)."""
        try:
            doc = json.loads(payload.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            return None
        if not isinstance(doc, dict):
            return None
        online, ts = doc.get("online"), doc.get("timestamp")
        if not isinstance(online, bool) or isinstance(ts, bool) or not isinstance(ts, int):
            return None
        if ts < self.timestamp:
            return None
        self.online, self.timestamp = online, ts
        return online


__all__ = ["NAMESPACE", "BdSeqStore", "EdgeSession", "HostState", "LatestValue", "millis"]
