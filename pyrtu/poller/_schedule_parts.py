"""The bus scheduler's records (schedule.py): a request to perform, a block's place
in the schedule, a slave's health, the bus's figures."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from .events import SlaveStats
from .plan import Block

POLL, PROBE, WRITE, READ = "poll", "probe", "write", "read"
_WRITE_FUNCTIONS = {("coils", True): 5, ("coils", False): 15, ("holding", True): 6,
                    ("holding", False): 16}  # fmt: skip


@dataclass(eq=False, slots=True)
class ScheduledRequest:
    """One transaction to perform.  ``kind``: poll, probe, write, read.  Reads:
    ``count`` registers or bits of ``table`` at ``address``; writes: ``values``
    (function 5/6 for one value, 15/16 for several)."""

    kind: str
    slave: int
    table: str
    address: int
    count: int
    function: int
    values: tuple[int | bool, ...] = ()
    block: Block | None = None
    tag: int = 0
    issued: float = 0.0
    cost: float = 0.0
    task: _Task | None = field(default=None, repr=False)


@dataclass(eq=False, slots=True)
class _Task:
    block: Block
    due: float
    cost: float
    late: float = 0.0
    alive: bool = True
    suspended: bool = False
    seq: int = 0
    #: the block's previous answer (its registers or bits): the same again is `Unchanged`
    raw: Sequence[int] | Sequence[bool] | None = None
    #: the seconds of the block's request and answer on the wire, without the
    #: turnaround (`Wire.read`; the wire of a scheduler does not change)
    frames: float = 0.0
    #: the block's function code (`Block.function`, looked up once)
    function: int = 0


@dataclass(slots=True)
class _Health:
    failures: int = 0
    offline: bool = False
    probe_due: float = 0.0
    backoff: float = 0.0
    probe: tuple[str, int] = ("holding", 0)
    turnaround: float | None = None
    probing: bool = False
    last_fail: int = -1  # the number of its last back-to-back failure (schedule._ended)
    silenced: object = None  # the request in flight when on_silence took it offline
    silent_from: float | None = None  # the end of its first unanswered request (at latest)


@dataclass
class _Stats:
    started: float | None = None
    busy: float = 0.0
    transactions: int = 0
    slaves: dict[int, SlaveStats] = field(default_factory=dict)


__all__ = ["POLL", "PROBE", "READ", "WRITE", "ScheduledRequest"]
