"""FC 43/14 device identification (streaming with More Follows, individual access,
conformity level, the CFW100 example) and the watchdog (P314 / parameter 413)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from types import ModuleType

import pytest
from ptylink import PtyLink, RawPort, ScriptedSlave, make_store, rtu, serving
from waiting import ANSWER_TIMEOUT

from pyrtu.drivers.master import Master
from pyrtu.drivers.slave import Slave
from pyrtu.pdu.errors import ExceptionResponseError, FrameError

OBJECTS = {
    0: b"pyrtu project",
    1: b"PR-1000",
    2: b"V2.31",
    3: b"https://example.invalid/pyrtu",
    4: b"Simulated drive",
    5: b"Model 1000",
    6: b"Application name of fair length",
    0x80: b"extended object one, twenty-seven bytes or so",
    0x81: b"E" * 40,
}


@pytest.fixture
def link() -> Iterator[PtyLink]:
    with PtyLink() as pty:
        yield pty


def test_cfw100_example(link: PtyLink) -> None:
    """CFW100 6.4 (request CRC corrected, see tests/vectors.py): basic information from
    object 02h; conformity 81h, one object, 'V1.00'."""
    ident = {0: b"WEG", 1: b"CFW100", 2: b"V1.00"}
    with (
        serving(link.path_b, store=make_store(), identification=ident),
        RawPort(link.path_a) as port,
    ):
        answer = port.ask(bytes.fromhex("01 2B 0E 01 02 F1 B6"), want=17)
        assert answer == bytes.fromhex("01 2B 0E 01 81 00 00 01 02 05 56 31 2E 30 30 3C 53")


def test_streaming_with_more_follows(link: PtyLink, backend: ModuleType) -> None:
    """max_adu=64 (the CFW100's telegram limit): the objects need several responses."""
    be = backend.BACKEND
    with (
        serving(
            link.path_b, store=make_store(), identification=OBJECTS, max_adu=64, backend=be, t35=0
        ),
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT, backend=be) as m,
    ):
        assert m.read_device_identification(1, 1) == {k: OBJECTS[k] for k in (0, 1, 2)}
        regular = m.read_device_identification(1, 2)
        assert regular == {k: v for k, v in OBJECTS.items() if k < 0x80}
        link.clear()
        assert m.read_device_identification(1, 3) == OBJECTS
        link.settle()
        assert m.counters["frame_errors"] == 0
        requests = [d for _t, d in link.writes("a")]
        assert len(requests) >= 5  # 229 bytes of objects, at most 52 per response
        answers = link.wire("b")
        assert max(len(d) for _t, d in link.writes("b")) <= 64
        assert answers[5:6] == b"\xff"  # the first page says More Follows
        # a stream starting at an object of the category, and individual access
        assert m.read_device_identification(1, 3, 0x80) == {
            0x80: OBJECTS[0x80],
            0x81: OBJECTS[0x81],
        }
        assert m.read_device_identification(1, 2, 0x99) == regular  # unknown: from 0
        assert m.read_device_identification(1, 4, 5) == {5: OBJECTS[5]}
        with pytest.raises(ExceptionResponseError) as info:
            m.read_device_identification(1, 4, 0x42)
        assert info.value.code == 2
        # conformity level: extended objects present, individual access: 0x83
        assert m.execute(1, 0x2B, b"\x0e\x04\x00")[2] == 0x83
        with pytest.raises(ExceptionResponseError) as info:
            m.execute(1, 0x2B, b"\x0e\x05\x00")
        assert info.value.code == 3


def test_conformity_levels_and_defaults(link: PtyLink) -> None:
    basic = Slave(link.path_b, parity="N")
    assert basic.identification.conformity == 0x81
    assert basic.identification.objects[0] == b"pyrtu"
    basic.close()
    regular = Slave(link.path_b, parity="N", identification={0: b"X", 0x10: b"Y"})
    assert regular.identification.conformity == 0x82
    assert regular.identification.objects[1] == b"pyrtu"  # missing basic objects filled
    regular.close()
    with pytest.raises(ValueError, match="fit a response"):
        Slave(link.path_b, parity="N", max_adu=64, identification={0x80: b"x" * 60})


def test_master_stops_a_next_object_loop(link: PtyLink) -> None:
    looping = rtu("01 2B 0E 01 81 FF 00 01 00 01 41")  # More Follows, next object 0, again

    with (
        ScriptedSlave(link.path_b, lambda request, n: [(0.0, looping)]),
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT) as m,
    ):
        with pytest.raises(FrameError, match="already read"):
            m.read_device_identification(1)


@pytest.mark.wall_clock
def test_watchdog(link: PtyLink, backend: ModuleType) -> None:
    """The watchdog trips `watchdog` seconds after the last valid telegram, once.

    Wall clock: requests 50 ms apart (a quarter of the 0.2 s watchdog) must keep it
    quiet, which a stall of 150 ms would break; on a loaded 2-core VM stalls are
    tens of ms.  The trip is checked within [0.95, 1.75] watchdog periods of the
    last answer: the slave re-armed a few ms before it (when the request came),
    and it looks at its watchdog at least every poll interval (50 ms).
    """
    calls: list[float] = []
    fired = threading.Event()

    def on_watchdog(slave: Slave) -> None:
        calls.append(time.monotonic())
        fired.set()

    be = backend.BACKEND
    with (
        serving(
            link.path_b,
            store=make_store(),
            t35=0,
            watchdog=0.2,
            on_watchdog=on_watchdog,
            backend=be,
        ) as s,
        Master(link.path_a, parity="N", t35=0, timeout=ANSWER_TIMEOUT, backend=be) as m,
        RawPort(link.path_a) as raw,
    ):
        time.sleep(0.35)
        assert calls == []  # not armed before the first valid telegram
        for _ in range(6):  # valid telegrams keep it quiet
            time.sleep(0.05)
            m.read_holding_registers(1, 0, 1)
        last = time.monotonic()
        assert calls == []
        raw.send(rtu("02 03 0000 0001"))  # not for this slave: does not re-arm
        bad = bytearray(rtu("01 03 0000 0001"))
        bad[-1] ^= 1
        time.sleep(0.05)
        raw.send(bytes(bad))  # bad CRC: does not re-arm
        assert fired.wait(1.0)
        assert 0.95 * 0.2 <= calls[0] - last <= 1.75 * 0.2  # watchdog=0.2
        time.sleep(0.3)
        assert len(calls) == 1  # once per lapse
        assert s.counters["watchdog_trips"] == 1
        m.write_register(0, 0, 1)  # a broadcast is a valid telegram: re-armed
        fired.clear()
        assert fired.wait(1.0)
        assert len(calls) == 2
    with pytest.raises(ValueError, match="watchdog"):
        Slave(link.path_b, parity="N", watchdog=0)
