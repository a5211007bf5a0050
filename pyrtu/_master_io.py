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
from ._slack import tighten_this_thread
from .port import Port, read_fd

_monotonic = time.monotonic
_QUIET, _SEND, _ANSWER = State.QUIET, State.SEND, State.ANSWER
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


def _nap(proto: ClientProtocol) -> bool:
    """Sleep until the bytes the answer still needs can all be in; True if it slept."""
    now = _monotonic()
    until = proto.ready_at(now)
    if until > now:
        _sleep(until - now)
        return True
    return False


def read_now(port: Port, fd: int) -> bytes:
    """What the descriptor has now (after a sleep on needed()): `read_fd` without a
    poll first; nothing read is looked at again through `Port.read` (its poll tells
    no input yet from a device that is gone)."""
    return read_fd(port, fd, False) or port.read(0)


def run_sync(port: Port, proto: ClientProtocol, call: Call) -> Any:
    """Run ``call`` through ``proto`` on ``port``; the result or the typed error."""
    slave, pdu, decode = call
    proto.start(slave, pdu, decode, _monotonic())
    fd = port.fd
    timed = proto.gap > 0  # bytes come at the character rate: sleep on needed()
    if timed:
        tighten_this_thread()  # silences and sleeps on needed() wake on time
    if fd is None:
        return _run_generic(port, proto)
    poll = port._poll.poll
    napped = False
    checked = False  # QUIET just found no input: SEND need not look again
    try:
        while True:
            state = proto.state
            if state is _ANSWER:
                # after a sleep the bytes are usually in: read first
                data = read_now(port, fd) if napped else b""
                if not data:
                    deadline = proto.deadline()
                    wait = 1.0 if deadline is None else deadline - _monotonic()
                    # poll(): millisecond timeouts are fine for the answer's deadline
                    if wait > 0 and poll(wait * 1000.0):
                        data = read_fd(port, fd, True)
                if data:
                    proto.receive_data(data, _monotonic())
                    napped = timed and proto.state is _ANSWER and _nap(proto)
                else:
                    napped = False
                    proto.handle_timer(_monotonic())
            elif state is _SEND:
                # pending input first (stale: it restarts the silence); one poll(0),
                # none right after QUIET's wait ended without input
                if not checked and poll(0) and (stale := read_fd(port, fd, True)):
                    proto.receive_data(stale, _monotonic())
                    continue
                checked = False
                start, end = port.write(proto.data_to_send())
                proto.transmitted(end, start)
                napped = timed and proto.state is _ANSWER and _nap(proto)
            elif state is _QUIET:
                checked = _quiet(port, proto, True)
                continue
            else:
                return proto.result()
    except BaseException:
        proto.abort(_monotonic())
        raise


def _quiet(port: Port, proto: ClientProtocol, has_fd: bool) -> bool:
    """QUIET: wait for the send time; input meanwhile is stale (it restarts the
    silence).  True when the wait ended without input (the line was just looked at)."""
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
        return False
    proto.handle_timer(now)
    return wait > 0


def send_request(port: Port, proto: ClientProtocol, checked: bool = False) -> bool:
    """SEND: pending input first (stale: fed to the protocol, which restarts the
    silence; False), else the request goes out and its end is reported (True).
    ``checked``: the caller found no input an instant ago (no second look)."""
    stale = b"" if checked else port.read(0)
    if stale:
        proto.receive_data(stale, _monotonic())
        return False
    start, end = port.write(proto.data_to_send())
    proto.transmitted(end, start)
    return True


def _run_generic(port: Port, proto: ClientProtocol) -> Any:
    """run_sync on a port without a file descriptor (URL ports, Windows): pyserial's
    timed reads, and on a timed line the sleep on needed() as run_sync."""
    timed = proto.gap > 0
    try:
        while True:
            state = proto.state
            if state is _ANSWER:
                deadline = proto.deadline()
                wait = 1.0 if deadline is None else deadline - _monotonic()
                data = port.read(max(wait, 0.0))
                if data:
                    proto.receive_data(data, _monotonic())
                    if timed and proto.state is _ANSWER:
                        _nap(proto)
                else:
                    proto.handle_timer(_monotonic())
            elif state is _SEND:
                if send_request(port, proto) and timed and proto.state is _ANSWER:
                    _nap(proto)
            elif state is _QUIET:
                _quiet(port, proto, False)
            else:
                return proto.result()
    except BaseException:
        proto.abort(_monotonic())
        raise
