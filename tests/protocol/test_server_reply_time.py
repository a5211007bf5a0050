"""The slave's answer goes out exactly t3.5 after the request's last byte, not one
microsecond sooner (Serial Line V1.02 §2.5.1.1: frames are separated by a silence of
at least 3.5 character times), whatever way the driver asks (`data_to_send`,
`next_action`, with a lead ``ahead``) and however the request's bytes came (one at a
time, in one chunk, in two).  Synthetic time: no port, no sleep.

t3.5 from the spec's arithmetic: 3.5 characters of 10 or 11 bits at 19200 baud and
below, 1.75 ms above; the request's end is the time its last byte was handed over
(the end of its character).  The core counts whole microseconds (t3.5 and the
character time rounded to the microsecond), so every time here is a whole number of
microseconds and the boundaries are exact to the nanosecond (the protocol adds
float seconds: its t3.5 may come out a rounding error of 1e-14 s late).
"""

from __future__ import annotations

from types import ModuleType

import pytest

from pyrtu import pdu
from pyrtu.core.line import LineConfig
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.protocol.datastore import DataStore
from pyrtu.protocol.server import Reply, ServerProtocol

#: (baudrate, parity, character, t3.5) in microseconds, by the spec
LINES = [
    (9600, "N", round(10e6 / 9600), round(3.5 * 10e6 / 9600)),
    (19200, "E", round(11e6 / 19200), round(3.5 * 11e6 / 19200)),
    (115200, "N", round(10e6 / 115200), 1750),
]
T0_US = 100_000_000  # 100 s
NS = 1e-9  # well below the microsecond: float rounding, never a character


def at(us: int) -> float:
    """``us`` microseconds in seconds (exact to the microsecond the core counts)."""
    s = us / 1e6
    assert round(s * 1_000_000) == us
    return s


def protocol(backend: ModuleType, baud: int, parity: str) -> tuple[ServerProtocol, bytes]:
    line = LineConfig(baudrate=baud, parity=parity)
    store = DataStore()
    store.holding_registers.add_range(0, [1000 + i for i in range(10)])
    app = SlaveBase(1, store, line=line, backend=backend.BACKEND)
    proto = ServerProtocol(line, app, backend=backend, state=app.line)
    request = bytes(backend.add_crc(b"\x01" + pdu.read_request(pdu.READ_HOLDING_REGISTERS, 0, 2)))
    return proto, request


def answer(backend: ModuleType) -> bytes:
    return bytes(backend.add_crc(b"\x01" + pdu.registers_response(3, [1000, 1001])))


def feed(proto: ServerProtocol, request: bytes, how: str, char: int) -> int:
    """Hand the request over ``how``; returns its last byte's time (us)."""
    if how == "bytewise":
        for i, b in enumerate(request):
            proto.receive_data(bytes((b,)), at(T0_US + i * char))
        return T0_US + (len(request) - 1) * char
    if how == "one chunk":
        proto.receive_data(request, at(T0_US))
        return T0_US
    proto.receive_data(request[:3], at(T0_US))  # two chunks, back to back on the wire
    end = T0_US + (len(request) - 3) * char
    proto.receive_data(request[3:], at(end))
    return end


CASES = [
    (baud, parity, bits, t35, how)
    for baud, parity, bits, t35 in LINES
    for how in ("bytewise", "one chunk", "two chunks")
]
IDS = [f"{baud}{parity}-{how.replace(' ', '_')}" for baud, parity, _bits, _t35, how in CASES]


@pytest.mark.parametrize(("baud", "parity", "char", "t35", "how"), CASES, ids=IDS)
def test_data_to_send_at_exactly_t35(
    backend: ModuleType, baud: int, parity: str, char: int, t35: int, how: str
) -> None:
    proto, request = protocol(backend, baud, parity)
    end = feed(proto, request, how, char)
    assert proto.data_to_send(at(end)) is None
    assert proto.data_to_send(at(end + t35 - 1)) is None  # one microsecond early: no
    assert proto.deadline() == pytest.approx(at(end + t35), abs=NS)
    assert proto.data_to_send(at(end + t35) + NS) == answer(backend)


@pytest.mark.parametrize(("baud", "parity", "char", "t35", "how"), CASES, ids=IDS)
@pytest.mark.parametrize("ahead", [0, 500])
def test_next_action_replies_at_exactly_t35(
    backend: ModuleType, baud: int, parity: str, char: int, t35: int, how: str, ahead: int
) -> None:
    """``next_action``: no `Reply` before t3.5 (less ``ahead``, for a driver that
    writes at a given time), and its ``at`` is t3.5 after the request's end."""
    proto, request = protocol(backend, baud, parity)
    end = feed(proto, request, how, char)
    for now in (end, end + t35 // 2, end + t35 - ahead - 1):
        action = proto.next_action(at(now), nap=False, ahead=ahead / 1e6)
        assert not isinstance(action, Reply), (now - end, action)
    action = proto.next_action(at(end + t35 - ahead) + NS, nap=False, ahead=ahead / 1e6)
    assert isinstance(action, Reply)
    assert action.data == answer(backend)
    assert action.at == pytest.approx(at(end + t35), abs=NS)
