"""Helpers of the TCP and gateway tests: a client that never reads its answers."""

from __future__ import annotations

import asyncio
import socket


def stuck_socket(address: tuple[str, int]) -> socket.socket:
    """A client socket with the smallest receive buffer the kernel allows (set before
    connecting, so the window stays small): it takes few answers before it is full."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    s.connect(address)
    s.setblocking(False)
    return s


async def flood(s: socket.socket, data: bytes, until_closed: float = 60.0) -> int:
    """Send ``data`` again and again, never reading, until the peer resets the
    connection; returns the bytes sent.  Fails if it is not closed in time.  A
    partial send is finished before ``data`` starts again, so the stream stays
    whole requests (resending all of ``data`` after a partial send would break
    the framing, and the gateway would close the client for a bad header).
    ``until_closed`` only bounds how long a failure takes: filling the kernel's
    and the gateway's buffers takes 1-2 s here, and many times that on a loaded
    machine (a 20 s bound failed there)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + until_closed
    sent = 0
    view = memoryview(data)
    at = 0  # where the next send starts in data
    while loop.time() < end:
        try:
            n = s.send(view[at:])
        except BlockingIOError:
            await asyncio.sleep(0.005)  # the gateway reads its requests: this passes
        except (ConnectionResetError, BrokenPipeError):
            return sent
        else:
            sent += n
            at = (at + n) % len(data)
            await asyncio.sleep(0)
    raise AssertionError(f"the stuck client was not closed ({sent} bytes sent)")
