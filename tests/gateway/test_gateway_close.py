"""`Gateway.close` ends every task even when a cancel is lost under it.

Python 3.11's ``asyncio.wait_for`` raises its operation's error instead of
CancelledError when both come at once: a bus being reopened (``AsyncTcpClient.connect``
under ``wait_for``, the connection refused) while the gateway closed lost the cancel
to the reopen's ``except OSError``, and the worker went on retrying: ``pyrtu gateway
--duration`` with a bus down hung at its end about one run in ten.  The bus here
loses the cancel the same way, every time."""

from __future__ import annotations

import asyncio
import threading

from pyrtu.drivers.reconnect import Backoff
from pyrtu.gateway import Gateway, GatewayLimits, ReopeningBus


def test_close_ends_a_worker_whose_reopen_swallows_the_cancel() -> None:
    async def main() -> None:
        attempts = 0
        reopening = asyncio.Event()

        async def opener() -> object:
            nonlocal attempts
            attempts += 1
            if attempts == 1:  # not there at the start: down, reopened on the back-off
                raise ConnectionRefusedError(111, "Connection refused")
            reopening.set()
            try:
                await asyncio.sleep(3600)
            except asyncio.CancelledError:  # as wait_for does when both come at once
                raise ConnectionRefusedError(111, "Connection refused") from None
            raise AssertionError("unreachable")

        bus = ReopeningBus("tcp://127.0.0.1:1", opener)
        limits = GatewayLimits(backoff=Backoff(initial=0.01, maximum=0.01))
        gateway = Gateway([(bus, [1])], limits)
        await gateway.start("127.0.0.1", 0)
        await asyncio.wait_for(reopening.wait(), 10)
        await asyncio.wait_for(gateway.close(), 10)  # hung before: the cancel was lost
        assert gateway.health() == ["the gateway is not running"]

    # in a thread of its own: before the fix, the loop never ended (a hang is a failure
    # here, not a stuck test run)
    errors: list[BaseException] = []

    def run() -> None:
        try:
            asyncio.run(main())
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(60)
    assert not thread.is_alive(), "the gateway's loop did not end: a worker outlived close()"
    if errors:
        raise errors[0]
