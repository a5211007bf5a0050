"""Closing an AsyncMaster hands the line on only when the answer of a cancelled
transaction is over: the next master to open the port would otherwise transmit
while the slave still answers (a collision the slave sees as another device at its
address; #27.15, the README's poller example)."""

from __future__ import annotations

import asyncio
import time
from types import ModuleType

import pytest
from ptylink import PtyLink, ScriptedSlave

from pyrtu import add_crc
from pyrtu.drivers.aio import AsyncMaster, run

LATE = 0.12  # the slave's late answer comes this long after the request
TIMEOUT = 0.3


def _answer(values: list[int]) -> bytes:
    body = bytes((1, 3, 2 * len(values))) + b"".join(v.to_bytes(2, "big") for v in values)
    return add_crc(body)


@pytest.mark.wall_clock
@pytest.mark.parametrize("path", ["first", "repeated"])
@pytest.mark.parametrize("answers", [True, False])
def test_close_waits_out_the_cancelled_transactions_answer(
    backend: ModuleType, path: str, answers: bool
) -> None:
    """``first``: the transaction is driven step by step; ``repeated``: the same
    request again goes as one Xfer on the xfer thread.  The cancelled request's
    answer comes LATE after it (``answers``) or never: close() returns after the
    answer's last byte (and the settling after it), or after the request's deadline
    when no byte comes; never while an answer may still be on its way."""
    cancelled = 1 if path == "repeated" else 0
    arrived: list[float] = []

    def answer(request: bytes, n: int) -> list[tuple[float, bytes]]:
        arrived.append(time.monotonic())
        if n != cancelled:
            return [(0.0, _answer([n]))]
        return [(LATE, _answer([n, n]))] if answers else []

    with PtyLink() as link, ScriptedSlave(link.path_b, answer):
        closed: list[float] = []
        asked: list[float] = []  # before the cancelled request went out

        async def main() -> None:
            m = AsyncMaster(
                link.path_a, parity="N", t35=0, timeout=TIMEOUT, backend=backend.BACKEND
            )
            try:
                if cancelled:
                    assert await m.read_holding_registers(1, 0, 1) == [0]
                asked.append(time.monotonic())
                with pytest.raises(asyncio.TimeoutError):
                    await asyncio.wait_for(m.read_holding_registers(1, 0, 1), 0.03)
            finally:
                await m.close()
                closed.append(time.monotonic())

        run(main())
        assert len(arrived) == cancelled + 1
        sent = arrived[cancelled]
        if answers:
            # the answer's 9 bytes went out LATE after the slave read the request; close()
            # saw them end, unless the request's deadline came first (a slave thread that a
            # loaded machine scheduled late answers after it: the master has given up then)
            assert closed[0] >= min(sent + LATE, asked[-1] + TIMEOUT)
            assert closed[0] < sent + TIMEOUT + 0.2  # and did not wait for the deadline
        else:
            # the deadline, TIMEOUT from the request's end (which was before `sent`, when the
            # slave had read it: up to a scheduling delay before)
            assert closed[0] >= sent + TIMEOUT - 0.1
