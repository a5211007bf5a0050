"""Master additions: request() (raw PDU in and out), line=, finite timeouts only."""

from __future__ import annotations

import os

import pytest
from ptylink import PtyLink, make_store, serving

from pyrtu import pdu as pdus
from pyrtu.core.line import LineConfig
from pyrtu.drivers import sync_io as mio
from pyrtu.drivers.master import Master
from pyrtu.pdu.errors import (
    ExceptionResponseError,
    ModbusError,
    NoResponseError,
    PortError,
)


def test_request_raw_pdu(backend: object) -> None:
    be = backend.BACKEND  # type: ignore[attr-defined]
    with PtyLink() as link, serving(link.path_b, store=make_store(), t35=0, backend=be):
        line = LineConfig(parity="N", t35=0)
        with Master(link.path_a, line=line, timeout=0.5, backend=be) as m:
            assert m.line is line and m.t35 == 0
            assert m.request(1, pdus.read_request(3, 2, 2)) == bytes.fromhex("030403ea03eb")
            assert m.request(1, pdus.write_register_request(5, 9)) == pdus.write_register_request(
                5, 9
            )
            assert m.request(0, pdus.write_register_request(6, 7)) == b""  # broadcast
            with pytest.raises(ExceptionResponseError) as info:
                m.request(1, pdus.read_request(3, 250, 1))
            assert info.value.code == 2 and info.value.function == 3
            assert m.last_answer_time is not None
            c = m.counters
            assert c["requests"] == 4 and c["responses"] == 2 and c["broadcasts"] == 1
            for bad, exc in (
                (b"", ValueError),
                (b"\x83\x00", ValueError),
                (bytes(254), ValueError),
                ("0300", TypeError),
            ):
                with pytest.raises(exc, match="request"):
                    m.request(1, bad)  # type: ignore[arg-type]
            with pytest.raises(ValueError, match="slave"):
                m.request(248, b"\x07")
            assert m.counters["requests"] == 4  # nothing was sent


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"timeout": float("inf")}, "timeout"),
        ({"timeout": float("nan")}, "timeout"),
        ({"timeout": -1}, "timeout"),
        ({"broadcast_delay": float("inf")}, "broadcast_delay"),
        ({"t35": float("inf")}, "t35"),
        ({"retries": 1.5}, "retries"),
    ],
)
def test_bad_options_refused_before_opening(kwargs: dict[str, object], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        Master("/dev/pyrtu-no-such-port", **kwargs)  # type: ignore[arg-type]


def test_line_and_keywords_are_exclusive() -> None:
    with pytest.raises(TypeError, match="baudrate"):
        Master("/dev/pyrtu-no-such-port", 9600, line=LineConfig())
    with pytest.raises(TypeError, match="LineConfig"):
        Master("/dev/pyrtu-no-such-port", line={"baudrate": 9600})  # type: ignore[arg-type]


def test_timeout_setter_is_checked() -> None:
    with PtyLink() as link, Master(link.path_a, parity="N", timeout=0.5) as m:
        m.timeout = 0.25
        assert m.timeout == 0.25
        with pytest.raises(ValueError, match="timeout"):
            m.timeout = float("inf")
        with pytest.raises(ValueError, match="retries"):
            m.retries = -1


def test_no_wake_per_byte_on_a_timed_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the virtual bus at 9600 baud (a 25-byte answer takes 26 ms), the master reads
    the answer in a few reads, not one per byte: it sleeps until the bytes the
    core's length prediction still needs can be in."""
    vbus = pytest.importorskip("pyrtu.vbus")
    with (
        vbus.VirtualBus(2, baudrate=9600, parity="N") as bus,
        serving(bus.paths[1], store=make_store(), baudrate=9600),
        Master(bus.paths[0], 9600, parity="N", timeout=1.0) as m,
    ):
        assert m.read_holding_registers(1, 0, 10) == [1000 + i for i in range(10)]
        reads: list[int] = []
        real_read = m.port.read
        real_ready = mio.read_fd

        def counting_read(timeout: float) -> bytes:
            data = real_read(timeout)
            if data:
                reads.append(len(data))
            return data

        def counting_ready(port: object, fd: int, readable: bool) -> bytes:
            data = real_ready(port, fd, readable)  # type: ignore[arg-type]
            if data:
                reads.append(len(data))
            return data

        m.port.read = counting_read  # type: ignore[method-assign]
        monkeypatch.setattr(mio, "read_fd", counting_ready)
        # a repeated request's xfer reads in the backend's XferRunner (one call)
        runner = m._conn.xfer_runner  # type: ignore[attr-defined]
        real_run = runner.run

        def counting_run(*args: object) -> object:
            r = real_run(*args)
            if r.reads:  # its bytes, and as many entries as it made reads
                reads.extend([len(r.data)] + [0] * (r.reads - 1))
            return r

        monkeypatch.setattr(runner, "run", counting_run)
        for _ in range(10):
            assert m.read_holding_registers(1, 0, 10) == [1000 + i for i in range(10)]
        assert sum(reads) == 10 * 25
        # one read per byte would be 250; sleeping on needed() takes 2-3 per answer
        # (scheduling delays on a loaded machine only merge reads further)
        assert len(reads) <= 10 * 8, reads


def test_cached_reads_still_check_their_arguments(backend: object) -> None:
    """The Calls of reads are cached by (function, slave, address, count): arguments
    equal to a cached key but of another type (True == 1, 1.0 == 1) must still fail
    their checks, and a different slave gets its own ADU (CRC)."""
    from pyrtu.pdu import requests as request_table
    from pyrtu.protocol.client import ClientProtocol

    good = request_table.read_holding_registers(1, 0, 10)
    assert request_table.read_holding_registers(1, 0, 10) is good  # cached
    for args in ((True, 0, 10), (1.0, 0, 10), (1, False, 10), (1, 0, 10.0)):
        with pytest.raises((TypeError, ValueError), match="read_holding_registers"):
            request_table.read_holding_registers(*args)
    assert request_table.read_input_registers(1, 0, 10).pdu[0] == 4  # the function is in the key
    proto = ClientProtocol(LineConfig(parity="N"), backend=backend)  # type: ignore[arg-type]
    adus = []
    for slave in (1, 2, 1):
        proto.start(slave, good.pdu, good.decode, 100.0)
        adus.append(proto.data_to_send())
        proto.abort(100.0)
    assert adus[0] == adus[2] != adus[1] and adus[1][0] == 2
    assert adus[0] == backend.add_crc(bytes((1,)) + good.pdu)  # type: ignore[attr-defined]


def test_unhashable_read_arguments_name_the_argument() -> None:
    from pyrtu.pdu import requests as request_table

    for args, name in (([1], 0, 10), "slave"), ((1, {}, 10), "address"):
        with pytest.raises(TypeError, match=name):
            request_table.read_coils(*args)  # type: ignore[arg-type]


def test_a_repeated_read_goes_as_one_xfer(backend: object) -> None:
    """On a descriptor, the second and later reads of a request are one call of the
    backend's XferRunner each (C or the twin): same answers, one xfer per read."""
    vbus = pytest.importorskip("pyrtu.vbus")
    name = backend.BACKEND  # type: ignore[attr-defined]
    with (
        vbus.VirtualBus(2, baudrate=115200, parity="N") as bus,
        serving(bus.paths[1], store=make_store(), baudrate=115200),
        Master(bus.paths[0], 115200, parity="N", timeout=1.0, backend=name) as m,
    ):
        runner = m._conn.xfer_runner  # type: ignore[attr-defined]
        assert type(runner).__module__.startswith(
            "pyrtu.drivers._cxfer" if name == "c" else "pyrtu.drivers._pyxfer"
        )
        calls = []
        real_run = runner.run

        def counting_run(*args: object) -> object:
            r = real_run(*args)
            calls.append(r)
            return r

        runner.run = counting_run
        for _ in range(10):
            assert m.read_holding_registers(1, 0, 10) == [1000 + i for i in range(10)]
        assert len(calls) >= 9 and all(r.sent for r in calls)
        assert m.counters["responses"] == 10 and m.counters["timeouts"] == 0


def test_a_drop_pulled_out_under_an_xfer_is_a_port_error(backend: object) -> None:
    """The master's drop vanishes while a repeated request is under way in the
    XferRunner: `PortError` naming the port (or no answer), never a hang; the master
    opened again on the replugged drop reads again."""
    vbus = pytest.importorskip("pyrtu.vbus")
    name = backend.BACKEND  # type: ignore[attr-defined]
    with (
        vbus.VirtualBus(2, baudrate=115200, parity="N") as bus,
        serving(bus.paths[1], store=make_store(), baudrate=115200),
    ):
        m = Master(bus.paths[0], 115200, parity="N", timeout=0.3, backend=name)
        try:
            for _ in range(3):
                assert m.read_holding_registers(1, 0, 1) == [1000]
            bus.unplug(0, after_bytes=3)
            with pytest.raises(ModbusError) as info:
                for _ in range(5):
                    m.read_holding_registers(1, 0, 1)
            assert isinstance(info.value, PortError | NoResponseError), info.value
            if isinstance(info.value, PortError):
                assert bus.paths[0] in str(info.value)
        finally:
            m.close()
        bus.replug(0)
        with Master(bus.paths[0], 115200, parity="N", timeout=0.5, backend=name) as again:
            assert again.read_holding_registers(1, 0, 1) == [1000]


@pytest.mark.wall_clock
def test_a_signal_ends_a_blocking_xfer_at_once(backend: object) -> None:
    """A signal's handler runs during a repeated read that waits in the XferRunner (C:
    with the GIL released) as it does in a Python sleep: the handler's exception ends
    the read at once, not at the 5 s deadline (bound: a tenth of it)."""
    import signal
    import threading
    import time

    vbus = pytest.importorskip("pyrtu.vbus")
    name = backend.BACKEND  # type: ignore[attr-defined]

    class Stop(Exception):
        pass

    def handler(signum: int, frame: object) -> None:
        raise Stop

    with vbus.VirtualBus(2, baudrate=115200, parity="N") as bus:
        m = Master(bus.paths[0], 115200, parity="N", timeout=5.0, backend=name)
        try:
            with serving(bus.paths[1], store=make_store(), baudrate=115200):
                for _ in range(3):  # the answer's length learned: xfers from now
                    assert m.read_holding_registers(1, 0, 1) == [1000]
            old = signal.signal(signal.SIGUSR1, handler)
            timer = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGUSR1))
            try:
                start = time.monotonic()
                timer.start()
                with pytest.raises(Stop):
                    m.read_holding_registers(1, 0, 1)  # nobody answers now
                assert time.monotonic() - start < 0.5
            finally:
                timer.cancel()
                signal.signal(signal.SIGUSR1, old)
        finally:
            m.close()
