"""The blocking driver of the client protocol: one transaction on a `Port`.

All policy (silences, echo, retries, late answers, settling) is in
`pyrtu._client.ClientProtocol`; this loop only writes, waits and reads.  While
an answer comes in it does not wake per byte: it sleeps until the bytes the
protocol still needs can all be in (``ready_at``: ``needed()`` character times,
from the core's length prediction, after the slave's t3.5), reads what is
there, and waits for input only when more is needed, with the protocol's
deadline as the safety net.
"""

from __future__ import annotations

import select
import time
from typing import Any

from ._client import ClientProtocol, State
from ._requests import Call
from .port import Port

_monotonic = time.monotonic
_sleep = time.sleep


def _wait_readable(port: Port, timeout: float) -> bool:
    """True when input is ready within ``timeout`` (microsecond resolution where
    select() takes the descriptor; poll()'s millisecond one rounds up)."""
    fd = port.fd
    if fd is None:
        return False
    if fd < 1024:
        return bool(select.select((fd,), (), (), max(timeout, 0.0))[0])
    return bool(port._poll.poll(max(timeout, 0.0) * 1000.0))


def _nap(proto: ClientProtocol) -> None:
    """Sleep until the bytes the answer still needs can all be in."""
    now = _monotonic()
    until = proto.ready_at(now)
    if until > now:
        _sleep(until - now)


def run_sync(port: Port, proto: ClientProtocol, call: Call) -> Any:
    """Run ``call`` through ``proto`` on ``port``; the result or the typed error."""
    proto.start(call.slave, call.pdu, call.decode, _monotonic())
    has_fd = port.fd is not None
    try:
        while True:
            state = proto.state
            if state is State.ANSWER:
                deadline = proto.deadline()
                now = _monotonic()
                wait = 1.0 if deadline is None else deadline - now
                if has_fd:
                    data = port.read(0)
                    if not data and wait > 0 and _wait_readable(port, wait):
                        data = port.read(0)
                else:
                    data = port.read(max(wait, 0.0))
                now = _monotonic()
                if not data:
                    proto.handle_timer(now)
                    continue
                proto.receive_data(data, now)
                if proto.state is State.ANSWER:
                    _nap(proto)
            elif state is State.SEND:
                stale = port.read(0)
                if stale:
                    proto.receive_data(stale, _monotonic())
                    continue
                start, end = port.write(proto.data_to_send())
                proto.transmitted(end, start)
                if proto.state is State.ANSWER:
                    _nap(proto)
            elif state is State.QUIET:
                deadline = proto.deadline()
                now = _monotonic()
                wait = 0.0 if deadline is None else deadline - now
                data = b""
                if wait > 0:
                    if has_fd:
                        if _wait_readable(port, wait):
                            data = port.read(0)
                    else:
                        data = port.read(wait)
                    now = _monotonic()
                if data:
                    proto.receive_data(data, now)
                else:
                    proto.handle_timer(now)
            else:
                return proto.result()
    except BaseException:
        proto.abort(_monotonic())
        raise
