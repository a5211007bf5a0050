"""The blocking drivers of the client protocol: one transaction on a `Port`.

All policy (silences, echo, retries, late answers, settling, when to sleep and
when to wait for input) is in `pyrtu.protocol.ClientProtocol`, which hands out one
action at a time (`Send`, `Wait`, `Xfer`, `Done`); `run_sync` interprets them,
with one way of waiting per kind of port: a descriptor (`_wait_fd`: sleeps,
``select()`` and ``poll()``) or pyserial's generic timed read (`_wait_generic`: URL
ports, Windows).  On a descriptor it asks for `Xfer`: a repeated request's
whole transaction in one call of the backend's `XferRunner` (C: csrc/rtu_xfer_io.c,
the GIL released), so that Python runs once per transaction instead of once per
wake-up.
"""

from __future__ import annotations

import os
import select
import time
from collections.abc import Callable
from typing import Any

from pyrtu.drivers import xfer
from pyrtu.drivers._slack import tighten_this_thread
from pyrtu.drivers.port import Port, read_fd
from pyrtu.pdu.errors import PortError
from pyrtu.pdu.requests import Call
from pyrtu.protocol.client import ClientProtocol, Send, Wait
from pyrtu.protocol.client_actions import Xfer

_monotonic = time.monotonic
_sleep = time.sleep


def read_now(port: Port, fd: int) -> bytes:
    """What the descriptor has now (after a sleep): `read_fd` without a poll first;
    nothing read is looked at again through `Port.read` (its poll tells no input
    yet from a device that is gone)."""
    return read_fd(port, fd, False) or port.read(0)


def _wait_fd(port: Port, fd: int, action: Wait) -> bytes:
    """A `Wait` on a descriptor: a sleep then one read (the bytes are due), or a
    wait for input: ``select()`` to the microsecond where nothing is awaited (the
    send time: stale input is read as it comes), else ``poll()`` (millisecond
    timeouts: fine for the deadline of an answer)."""
    until, listen, needed = action
    wait = until - _monotonic()
    if not (listen or needed):
        if fd < 1024:
            ready = bool(select.select((fd,), (), (), wait if wait > 0 else 0.0)[0])
        else:
            ready = port.readable(wait)
        return read_fd(port, fd, True) if ready else b""
    if not listen:
        if wait > 0:
            _sleep(wait)
        return read_now(port, fd)
    if port.readable(wait):
        return read_fd(port, fd, True)
    return b""


def _wait_generic(port: Port, action: Wait) -> bytes:
    """A `Wait` through pyserial's timed reads (ports without a descriptor)."""
    wait = action.until - _monotonic()
    if action.listen:
        return port.read(wait if wait > 0 else 0.0)
    if wait > 0:
        _sleep(wait)
    return port.read(0)


def waiter(port: Port) -> Callable[[Wait], bytes]:
    """The port's way of carrying out a `Wait`: the bytes read (b"": none)."""
    fd = port.fd
    if fd is None:
        return lambda action: _wait_generic(port, action)
    return lambda action: _wait_fd(port, fd, action)


def plan_of(port: Port, fd: int, action: Xfer) -> xfer.XferPlan:
    """An `Xfer` on ``port`` as the xfer runners take it."""
    return xfer.XferPlan(fd, port.has_wire, port.char_time, action)


def report(port: Port, proto: ClientProtocol, r: xfer.XferResult) -> None:
    """Tell ``proto`` what an xfer saw (``xfer_done``; ``wait_done`` for input
    found at the send time); `PortError` as `Port.read` and `Port.write` raise them
    (what a failed read read is not reported)."""
    status = r.status
    failed = status == xfer.ERRNO or status == xfer.GONE
    if r.sent:
        if failed:
            proto.xfer_done(r.start, r.end, b"", 0, r.end, r.end)
        else:
            proto.xfer_done(r.start, r.end, r.data, r.first_n, r.first_t, r.last_t)
    elif not failed:
        data = r.data
        proto.wait_done(data, r.last_t if data else _monotonic())
    if status == xfer.ERRNO:
        what = "write" if r.stage == xfer.STAGE_WRITE else "read"
        raise PortError(port.name, f"{what} failed: {OSError(r.err, os.strerror(r.err))}")
    if status == xfer.GONE:
        raise PortError(port.name, "the device reports data but returns none (disconnected?)")


def run_sync(port: Port, proto: ClientProtocol, call: Call, xfer_runner: Any = None) -> Any:
    """Run ``call`` through ``proto`` on ``port``; the result or the typed error.
    ``xfer_runner``: the backend's `pyrtu.drivers.xfer.XferRunner` for this port (None: the
    steps one by one)."""
    slave, pdu, decode = call
    proto.start(slave, pdu, decode, _monotonic())
    if proto.gap > 0:
        tighten_this_thread()  # silences and sleeps on ready_at wake on time
    fd = port.fd
    run = xfer_runner.run if xfer_runner is not None and fd is not None else None
    wait: Callable[[Wait], bytes] | None = None
    try:
        while True:
            action = proto.next_action(_monotonic(), run is not None)
            if isinstance(action, Xfer):
                assert fd is not None and run is not None
                report(port, proto, run(plan_of(port, fd, action)))
                if proto.done:  # (the common end: the result without a Done)
                    return proto.result()
            elif isinstance(action, Wait):
                if wait is None:
                    wait = waiter(port)
                data = wait(action)
                proto.wait_done(data, _monotonic())
            elif isinstance(action, Send):
                start, end = port.write(action.data)
                proto.transmitted(end, start)
            else:
                break
    except BaseException:
        proto.abort(_monotonic())
        raise
    return action.result()
