"""One `Master` class (and one `AsyncMaster`) whatever the transport, the port string
picking its link; one table of requests behind both and the poller; the line
keywords checked the same way on every transport (issue 18, items 3 and 4)."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import time

import pytest
from ptylink import PtyLink, make_store, serving

from pyrtu.core.line import LINE_DEFAULTS, LineConfig, line_from
from pyrtu.drivers.aio import AsyncMaster
from pyrtu.drivers.master import Master
from pyrtu.pdu import requests as request_table
from pyrtu.pdu.errors import PortError
from pyrtu.poller.masters import ThreadMaster

#: ports nothing listens on: the keywords must be refused before any connection
TCP = "tcp://127.0.0.1:1"
RTU_TCP = "rtu+tcp://127.0.0.1:1"


def test_import_pyrtu_loads_neither_poller_nor_asyncio() -> None:
    """``import pyrtu`` registers nothing by side effect: the poller, the asyncio
    master and asyncio itself load only when used; ``pyrtu.Poller``,
    ``pyrtu.AsyncMaster`` and ``pyrtu.AsyncSlave`` still work (one public path each)."""
    probe = (
        "import pyrtu, sys\n"
        "loaded = [m for m in ('pyrtu.poller', 'pyrtu.drivers.aio', 'pyrtu.tcp', 'pyrtu.tcp.link',"
        " 'asyncio') if m in sys.modules]\n"
        "assert not loaded, loaded\n"
        "m = pyrtu.Master\n"
        "assert 'asyncio' not in sys.modules\n"
        "from pyrtu.poller import Poller\n"
        "assert pyrtu.Poller is Poller and 'Poller' in pyrtu.__all__\n"
        "assert not hasattr(pyrtu, 'NoSuchName')\n"
        "from pyrtu.drivers.aio import AsyncMaster\n"
        "from pyrtu.drivers.aio_slave import AsyncSlave\n"
        "assert pyrtu.AsyncMaster is AsyncMaster and pyrtu.AsyncSlave is AsyncSlave\n"
        "assert {'AsyncMaster', 'AsyncSlave'} <= set(pyrtu.__all__)\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=False
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_one_class_no_new_dispatch() -> None:
    """No ``__new__`` picks a subclass: the master's class is the one called."""
    assert "__new__" not in vars(Master) and "__new__" not in vars(AsyncMaster)
    am = AsyncMaster(TCP)  # connects on first use
    assert type(am) is AsyncMaster and am.mode == "tcp" and am.url == TCP
    with pytest.raises(PortError, match="cannot connect"):
        Master(TCP)  # the blocking client connects now (nothing listens)


@pytest.mark.parametrize("port", [TCP, RTU_TCP, "/dev/pyrtu-no-such-port"])
@pytest.mark.parametrize("cls", [Master, AsyncMaster])
def test_unknown_keyword_is_a_type_error_on_every_transport(
    cls: type[Master] | type[AsyncMaster], port: str
) -> None:
    """A misspelled keyword is a TypeError naming it, before the port is opened or
    the connection tried (it passed silently on tcp://)."""
    with pytest.raises(TypeError, match="bogus"):
        cls(port, bogus=1)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="baudrat"):
        cls(port, baudrat=9600)  # type: ignore[call-arg]


@pytest.mark.parametrize("port", [TCP, RTU_TCP])
def test_line_keywords_are_checked_on_tcp_too(port: str) -> None:
    """A bad line value and ``line=`` with keywords get the serial master's errors on
    every transport, before connecting (a TCP master ignored them)."""
    for cls in (Master, AsyncMaster):
        with pytest.raises(ValueError, match="baudrate must be"):
            cls(port, baudrate=0)
        with pytest.raises(TypeError, match="not both"):
            cls(port, line=LineConfig(), parity="N")
        with pytest.raises(ValueError, match="broadcast_delay"):
            cls(port, broadcast_delay=-1)
    with pytest.raises(ValueError, match="max_in_flight"):
        Master(port, max_in_flight=2)  # the sync master sends one at a time


def test_line_from_is_the_one_rule() -> None:
    """One function turns keywords into a LineConfig; one table holds the defaults
    (the LineConfig's own)."""
    assert LINE_DEFAULTS["baudrate"] == LineConfig().baudrate == 19200
    assert LINE_DEFAULTS["parity"] == "E" and LINE_DEFAULTS["rules"] is None
    line = LineConfig(baudrate=9600)
    assert line_from(line, **{k: v for k, v in LINE_DEFAULTS.items() if k != "rules"}) is line
    assert line_from(None, baudrate=9600, rules=None) == line
    with pytest.raises(TypeError, match="give line= or the line keywords \\(mode\\)"):
        line_from(line, mode="ascii")
    with pytest.raises(TypeError, match=r"unexpected keyword argument .colour."):
        line_from(None, colour="red")
    with pytest.raises(TypeError, match="line must be a LineConfig"):
        line_from("9600,8N1")  # type: ignore[arg-type]


def test_transact_gives_value_and_answer_time(backend: object) -> None:
    """``transact`` runs a request of the one table and returns the answer's end time
    with the value (what the poller stamps values with); the sync, asyncio and
    thread masters agree."""
    be = backend.BACKEND  # type: ignore[attr-defined]
    with PtyLink() as link, serving(link.path_b, store=make_store(), t35=0, backend=be):
        line = LineConfig(parity="N", t35=0)
        with Master(link.path_a, line=line, timeout=0.5, backend=be) as m:
            before = time.monotonic()
            value, end = m.transact(request_table.BY_FUNCTION[3], 1, 2, 3)
            assert value == [1002, 1003, 1004]
            assert end == m.last_answer_time and before <= end <= time.monotonic()
            value, end = m.transact("write_register", 0, 5, 9)  # broadcast: no answer
            assert value is None and end >= before
            assert m.transact("read_device_identification", 1, 1)[0][0] == b"pyrtu"

            async def threaded() -> tuple[object, float]:
                tm = ThreadMaster(m)
                return await tm.transact(request_table.BY_FUNCTION[4], 1, 0, 2)

            value, end = asyncio.run(threaded())
            assert value == [2000, 2001] and end == m.last_answer_time

        async def main() -> None:
            async with AsyncMaster(link.path_a, line=line, timeout=0.5, backend=be) as am:
                value, end = await am.transact(request_table.BY_FUNCTION[1], 1, 0, 4)
                assert value == [True, False, False, True]
                assert end == am.last_answer_time
                # the generated methods: same names, docstrings and answers as Master's
                assert am.read_holding_registers.__doc__ == Master.read_holding_registers.__doc__
                assert await am.read_holding_registers(1, 2, 1) == [1002]
                assert await am.diagnostics(1, 0, 0x1234) == 0x1234

        asyncio.run(main())


def test_tcp_master_has_no_port_but_says_why() -> None:
    """``.line`` and ``.port`` on a TCP link: AttributeError naming the URL."""
    m = AsyncMaster(TCP)  # connects on first use
    for name in ("line", "port"):
        with pytest.raises(AttributeError, match=re.escape(TCP)):
            getattr(m, name)
    with pytest.raises(PortError):
        asyncio.run(m.read_coils(1, 0, 1))


def test_poller_opens_its_master_from_the_bus_line() -> None:
    """The poller's bus makes its LineConfig once; the master it opens uses that very
    object (it was opened from the raw keywords, validating them again)."""
    from pyrtu.poller import Bus
    from pyrtu.poller.masters import open_async_master
    from pyrtu.vbus import VirtualBus

    with VirtualBus(2, parity="N") as vbus:
        bus = Bus("b", vbus.paths[0], {"parity": "N", "baudrate": 19200, "timeout": 0.3})
        assert bus.master_options == {"timeout": 0.3}

        async def main() -> None:
            master = open_async_master(bus)
            try:
                assert master.line is bus.line  # type: ignore[attr-defined]
            finally:
                await master.close()

        asyncio.run(main())
    rtu_tcp = Bus("r", RTU_TCP, {"parity": "N"})
    assert rtu_tcp.line.t35 == 0  # priced as the master runs it: no wire timing
