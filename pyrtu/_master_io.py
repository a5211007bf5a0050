"""The blocking driver of the client protocol: one transaction on a `Port`.

All policy (silences, echo, retries, late answers, settling) is in
`pyrtu._client.ClientProtocol`; this loop only writes, waits and reads.  While
an answer is coming in it wakes once for the first bytes, then sleeps the
character times of the bytes the protocol still needs (``needed()``), with the
protocol's deadline as the safety net, instead of waking per byte.
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


def run_sync(port: Port, proto: ClientProtocol, call: Call) -> Any:
    """Run ``call`` through ``proto`` on ``port``; the result or the typed error."""
    proto.start(call.slave, call.pdu, call.decode, _monotonic())
    char = proto.line.char_time
    has_fd = port.fd is not None
    try:
        while True:
            state = proto.state
            if state is State.ANSWER:
                deadline = proto.deadline()
                now = _monotonic()
                wait = 1.0 if deadline is None else deadline - now
                if wait <= 0:
                    proto.handle_timer(now)
                    continue
                if has_fd:
                    data = port.read(0) if _wait_readable(port, wait) else b""
                else:
                    data = port.read(wait)
                now = _monotonic()
                if not data:
                    proto.handle_timer(now)
                    continue
                proto.receive_data(data, now)
                if proto.state is State.ANSWER:
                    need = proto.needed()
                    if need > 0:
                        deadline = proto.deadline()
                        nap = need * char
                        if deadline is not None:
                            nap = min(nap, deadline - now)
                        if nap > 0:
                            _sleep(nap)
            elif state is State.SEND:
                stale = port.read(0)
                if stale:
                    proto.receive_data(stale, _monotonic())
                    continue
                start, end = port.write(proto.data_to_send())
                proto.transmitted(end, start)
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
