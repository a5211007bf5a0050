"""The client protocol drives the ASCII framer through its core, as it drives RTU's:
the cores keep one feed/take contract (``expect`` starts a fresh framer for the
answer), so a retry or a new transaction never sees what an earlier one left."""

from __future__ import annotations

from types import ModuleType

from pyrtu.core.ascii import AsciiCore, encode_ascii
from pyrtu.core.line import LineConfig
from pyrtu.pdu.requests import read_holding_registers
from pyrtu.protocol.client import ClientProtocol, ClientState

ASCII = LineConfig(mode="ascii", parity="N")


def test_ascii_core_expect_starts_a_fresh_framer_as_the_rtu_core(backend: ModuleType) -> None:
    answer = encode_ascii(bytes.fromhex("01030400070008"))
    core = AsciiCore("master", 1_000_000)
    core.feed(answer[:7], 1_000)
    core.expect(encode_ascii(bytes.fromhex("010300000002")))
    assert core.deadline() is None  # the partial frame is gone, no timer left
    core.feed(answer, 2_000)
    assert core.take() == (0, 2_000, answer)
    assert core.take() is None
    assert core.counts()[1] == [0] * len(core.counts()[1])  # nothing discarded
    rtu = backend.Framer("master", line=LineConfig(baudrate=9600)).core
    rtu.feed(b"\x01\x03\x04\x00", 1_000)
    rtu.expect(bytes(backend.add_crc(bytes.fromhex("010300000002"))))
    assert rtu.deadline() is None


def test_ascii_retry_does_not_see_the_partial_answer_of_the_failed_attempt(
    backend: ModuleType,
) -> None:
    p = ClientProtocol(ASCII, timeout=0.5, retries=1, backend=backend)
    p.start(*read_holding_registers(1, 0, 2), now=1.0)
    assert p.next_action(1.0).__class__.__name__ == "Wait"  # the look for stale input
    p.wait_done(b"", 1.0)
    p.transmitted(1.01, 1.0)
    answer = encode_ascii(bytes.fromhex("01030400070008"))
    p.receive_data(answer[:9], 1.1)  # the slave stops mid-frame
    p.handle_timer(1.52)  # the attempt's limit, before the 1 s inter-character limit
    assert p.state is not ClientState.DONE  # retried
    while p.state is not ClientState.SEND:
        p.handle_timer(p.deadline() or 1.6)
    p.wait_done(b"", 1.6)
    p.transmitted(1.61, 1.6)
    p.receive_data(answer, 1.7)
    assert p.result() == [7, 8]
    assert p.counters["discarded_bytes"] == 0
