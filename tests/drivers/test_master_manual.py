"""The manuals' worked examples (tests/vectors.py): the master's methods put the
manuals' request bytes on the wire exactly, and read the manuals' answers back as the
manuals explain them (values, echoes, exception codes)."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import pytest
from ptylink import PtyLink, ScriptedSlave
from vectors import TELEGRAMS, Telegram

from pyrtu import BONFIGLIOLI, decode_ascii
from pyrtu.drivers.master import Master
from pyrtu.pdu.errors import ExceptionResponseError


def _message(t: Telegram) -> bytes:
    return t.adu[:-2] if t.mode == "rtu" else decode_ascii(t.adu)


def _pairs() -> Iterator[tuple[Telegram, Telegram]]:
    for request, answer in itertools.pairwise(TELEGRAMS):
        if request.kind == "request" and answer.kind != "request" and answer.mode == request.mode:
            yield request, answer


PAIRS = list(_pairs())


def _u16(data: bytes, at: int) -> int:
    return int.from_bytes(data[at : at + 2], "big")


def _call(m: Master, message: bytes) -> object:
    slave, fc, data = message[0], message[1], message[2:]
    if fc == 3:
        return m.read_holding_registers(slave, _u16(data, 0), _u16(data, 2))
    if fc == 6:
        return m.write_register(slave, _u16(data, 0), _u16(data, 2))
    if fc == 16:
        values = [_u16(data, 5 + 2 * i) for i in range(_u16(data, 2))]
        return m.write_registers(slave, _u16(data, 0), values)
    if fc == 8:
        return m.diagnostics(slave, _u16(data, 0), _u16(data, 2))
    if fc == 43:
        return m.read_device_identification(slave, data[1], data[2])
    if fc in BONFIGLIOLI:
        req, resp = BONFIGLIOLI[fc]
        return m.execute(slave, fc, data, request_rule=req, response_rule=resp)
    raise AssertionError(f"no master method for function {fc}")


def _expected(request: bytes, answer: bytes) -> object:
    fc, data = answer[1], answer[2:]
    if fc == 3:
        return [_u16(data, 1 + 2 * i) for i in range(data[0] // 2)]
    if fc in (6, 16):
        return None
    if fc == 8:
        return _u16(data, 2)
    if fc == 43:
        objects, pos = {}, 6
        for _ in range(data[5]):
            objects[data[pos]] = data[pos + 2 : pos + 2 + data[pos + 1]]
            pos += 2 + data[pos + 1]
        return objects
    return data  # vendor codes: the response data


def test_every_example_is_covered() -> None:
    requests = [t for t in TELEGRAMS if t.kind == "request"]
    assert len(PAIRS) == len(requests) >= 30


@pytest.mark.parametrize(
    ("request_t", "answer_t"), PAIRS, ids=[f"{r.source}:{r.where[:40]}" for r, _a in PAIRS]
)
def test_manual_example(request_t: Telegram, answer_t: Telegram) -> None:
    with PtyLink() as link:
        answer_bytes = answer_t.adu
        with (
            ScriptedSlave(link.path_b, lambda request, n: [(0.0, answer_bytes)]) as peer,
            Master(link.path_a, parity="N", t35=0, timeout=0.5, mode=request_t.mode) as m,
        ):
            request, answer = _message(request_t), _message(answer_t)
            if answer_t.kind == "exception":
                with pytest.raises(ExceptionResponseError) as info:
                    _call(m, request)
                assert (info.value.slave, info.value.function, info.value.code) == (
                    answer[0],
                    answer[1] & 0x7F,
                    answer[2],
                )
            else:
                assert _call(m, request) == _expected(request, answer)
            assert peer.requests == [request_t.adu]
