"""Helpers shared by the outbox tests (tests/test_bridge_outbox*.py)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from pyrtu.outbox.outbox import Outbox, OutboxLimits

SMALL = OutboxLimits(max_bytes=1 << 20, segment_bytes=4096)


def payload(seq: int) -> bytes:
    """A record whose content is known from its sequence number (length 1..64)."""
    digest = hashlib.blake2b(str(seq).encode(), digest_size=32).digest()
    return (digest * 2)[: 1 + seq % 64]


def fill(ob: Outbox, n: int, t0: float = 0.0) -> list[int]:
    seqs = []
    for i in range(n):
        seqs.append(ob.append(payload(ob.next_seq), t0 + i))
    return seqs


def everything(ob: Outbox, after: int | None = None) -> list[tuple[int, bytes]]:
    out: list[tuple[int, bytes]] = []
    while True:
        batch = ob.pending(97, after=out[-1][0] if out else after)
        if not batch:
            return out
        out.extend(batch)


def segments(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.suffix == ".seg")


def run_child(code: str, *args: str) -> subprocess.CompletedProcess[bytes]:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, env=env
    )
