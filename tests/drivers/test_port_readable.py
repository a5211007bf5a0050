"""`Port.readable`: the public wait for input the blocking client driver uses (it read
the port's private poll object before), and the slave's option checks made before
its port is opened, now through the line's options (no framer built for them)."""

from __future__ import annotations

import os

import pytest

from pyrtu import Slave
from pyrtu.drivers.port import open_port

pytest_plugins = ["peers.fixtures"]


def test_port_readable_waits_for_input_on_a_pty(pty_pair: tuple[str, str]) -> None:
    a = open_port(pty_pair[0], baudrate=115200, parity="N")
    b = open_port(pty_pair[1], baudrate=115200, parity="N")
    try:
        assert a.fd is not None
        assert a.readable(0) is False
        assert a.readable(0.01) is False
        b.write(b"\x01\x02")
        assert a.readable(2.0) is True
        assert a.read(0) == b"\x01\x02"
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize(
    ("keywords", "message"),
    [
        ({"t35": 1e13}, "t35 must be at most"),
        ({"flush_timeout": 1e13}, "flush_timeout must be at most"),
    ],
)
def test_slave_checks_the_core_limits_before_opening_its_port(
    tmp_path: str, keywords: dict[str, float], message: str
) -> None:
    missing = os.path.join(tmp_path, "no-such-port")
    with pytest.raises(ValueError, match=message):
        Slave(missing, 1, parity="N", **keywords)  # type: ignore[arg-type]
