"""Every worked example of every manual against its simulator, byte for byte.

Each request ADU of `tests.vectors` goes to a simulator in its default state (a fresh
one per example: the manuals' examples are independent of each other) and the
response ADU must equal the manual's (errata corrected, see vectors.py), in RTU and,
where the manual has them, ASCII:

* directly: the simulator's `pyrtu.Slave` on a ``loop://`` port, one `Slave.poll`
  per request (no timing, sub-millisecond);
* over the virtual RS-485 bus: a raw pyserial port on one drop, the simulator's
  slave on another, with the drive's own response delay.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
import serial

from pyrtu.devices import DriveSimulator, simulator
from pyrtu.vbus import VirtualBus
from tests.vectors import TELEGRAMS, Telegram

#: manual source -> simulator names that must reproduce its examples
SOURCES = {
    "CFW100": ("cfw100",),
    "CFW701": ("cfw701", "cfw320"),  # the CFW320 manual prints none; the WEG ones apply
    "CV100": ("cv100",),
    "ACT/ACU": ("act", "acu"),
}


def _pairs() -> Iterator[tuple[Telegram, Telegram]]:
    for i, t in enumerate(TELEGRAMS):
        if t.kind == "request":
            reply = TELEGRAMS[i + 1]
            assert reply.kind in ("response", "exception") and reply.source == t.source
            yield t, reply


PAIRS = list(_pairs())
PLAIN = [(device, req, resp) for req, resp in PAIRS for device in SOURCES[req.source]]
CASES = [pytest.param(d, q, r, id=f"{d}-{q.mode}-{q.where[:48]}") for d, q, r in PLAIN]


def _unit(t: Telegram) -> int:
    return int(t.adu[1:3], 16) if t.mode == "ascii" else t.adu[0]


def _sim(device: str, mode: str) -> DriveSimulator:
    return simulator(device, mode=mode) if mode == "ascii" else simulator(device)


def test_every_telegram_is_covered() -> None:
    """No worked example is left out: every telegram is a request with its reply, or
    the one standalone LRC example (checked below)."""
    paired = {id(t) for pair in PAIRS for t in pair}
    left = [t for t in TELEGRAMS if id(t) not in paired]
    assert [t.where[:5] for t in left] == ["6.7.2"]
    assert len(PAIRS) == 38 and len(CASES) == 60
    assert {t.source for t in TELEGRAMS} == set(SOURCES)


@pytest.mark.parametrize(("device", "request_", "response"), CASES)
def test_example_direct(device: str, request_: Telegram, response: Telegram) -> None:
    sim = _sim(device, request_.mode)
    slave = sim.make_slave("loop://", _unit(request_), parity="N", t35=0, response_delay=0)
    try:
        slave.port.write(request_.adu)
        slave.poll(0.2)
        got = slave.port.read(0.2)
        assert got == response.adu, f"{request_.where}: {got!r} != {response.adu!r}"
        assert sim.telegrams == 1
    finally:
        slave.close()


def test_standalone_lrc_example() -> None:
    """6.7.2.3 (LRC worked example): the exception frame ``:0183027A`` is what the
    ACT answers to FC 3 with No. of Regs = 2 in ASCII."""
    (lrc_example,) = [t for t in TELEGRAMS if t.where.startswith("6.7.2.3")]
    sim = _sim("act", "ascii")
    slave = sim.make_slave("loop://", 1, parity="N", t35=0, response_delay=0)
    try:
        slave.port.write(b":01030174000285\r\n")
        slave.poll(0.2)
        assert slave.port.read(0.2) == lrc_example.adu
    finally:
        slave.close()


def _exchange(port: serial.Serial, adu: bytes, expected: int, timeout: float = 1.0) -> bytes:
    port.reset_input_buffer()
    port.write(adu)
    got = b""
    deadline = time.monotonic() + timeout
    while len(got) < expected and time.monotonic() < deadline:
        got += port.read(expected - len(got))
    return got


@pytest.mark.parametrize("mode", ["rtu", "ascii"])
def test_examples_over_the_bus(mode: str) -> None:
    """All examples of one mode over ptys, each against a fresh simulator in its
    default state; the response also keeps the drive's minimum response delay."""
    cases = [(d, q, r) for d, q, r in PLAIN if q.mode == mode]
    assert cases
    with VirtualBus(2, baudrate=38400, parity="N") as bus:
        port = serial.Serial(bus.paths[0], 38400, timeout=0.05)
        try:
            for device, req, resp in cases:
                sim = _sim(device, mode)
                slave = sim.serve(bus.paths[1], _unit(req), baudrate=38400, parity="N")
                try:
                    started = time.monotonic()
                    got = _exchange(port, req.adu, len(resp.adu))
                    took = time.monotonic() - started
                finally:
                    sim.close()
                assert got == resp.adu, f"{device} {req.where}: {got!r} != {resp.adu!r}"
                # A lower bound only (a loaded machine can only add to it): no
                # wall_clock marker, the sanitizer run keeps this test.
                assert took >= slave.response_delay
        finally:
            port.close()
