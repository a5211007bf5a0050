"""`Port.write` on a pseudo-terminal when the output buffer fills: the rest is
written as the other side reads (`_write_rest`), a buffer that stays full ends in a
`PortError` at the deadline, and a failed write is a `PortError` naming the port.

Real ptys (no mock): the master end of the pair is read, or not, by the test."""

from __future__ import annotations

import gc
import os
import pty
import threading
from collections.abc import Iterator

import pytest

from pyrtu.drivers.port import Port, open_port
from pyrtu.pdu.errors import PortError

BAUD = 921600
#: more than a pty's buffer holds (about 15 KiB here), so the first os.write is partial
SIZE = 70_000


@pytest.fixture
def pty_port() -> Iterator[tuple[int, Port]]:
    master, slave = pty.openpty()
    port = open_port(os.ttyname(slave), baudrate=BAUD, parity="N")
    os.close(slave)
    try:
        yield master, port
    finally:
        port.close()
        os.close(master)


def test_a_write_larger_than_the_buffer_arrives_whole_and_in_order(
    pty_port: tuple[int, Port],
) -> None:
    master, port = pty_port
    data = bytes(range(256)) * (SIZE // 256)
    got = bytearray()

    def drain() -> None:
        while len(got) < len(data):
            got.extend(os.read(master, 65536))

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    start, end = port.write(data)
    reader.join(timeout=30)
    assert bytes(got) == data
    assert start <= end


@pytest.mark.wall_clock
def test_a_buffer_that_stays_full_is_a_port_error_at_the_deadline(
    pty_port: tuple[int, Port],
) -> None:
    # nobody reads the master end: the deadline is 1 s + two character times a byte
    _, port = pty_port
    with pytest.raises(PortError, match=r"write timed out with \d+ bytes unsent"):
        port.write(b"\x55" * SIZE)


def test_a_failed_write_is_a_port_error_naming_the_port(pty_port: tuple[int, Port]) -> None:
    _, port = pty_port
    assert port.fd is not None
    os.close(port.fd)  # the descriptor is gone under the port: os.write fails (EBADF)
    with pytest.raises(PortError, match="write failed") as info:
        port.write(b"ab")
    assert port.name in str(info.value)


def test_closing_a_port_whose_descriptor_vanished_never_closes_its_number_again() -> None:
    """The descriptor closed under the port (as above), then `Port.close`: pyserial's
    own close fails on it and used to leave its object open, holding the number; when
    the object was collected, io.IOBase's finalizer closed that number again, by then
    another file's (an event loop's timer descriptor: uvloop aborted the whole test
    run).  Now the port's object is closed and its abort pipes with it."""
    master, slave = pty.openpty()
    port = open_port(os.ttyname(slave), baudrate=BAUD, parity="N")
    os.close(slave)
    try:
        fd = port.fd
        assert fd is not None
        pipes = [port.serial.pipe_abort_read_r, port.serial.pipe_abort_write_w]
        os.close(fd)
        port.close()
        assert not port.serial.is_open
        for p in pipes:  # pyserial's abort pipes are not left behind
            with pytest.raises(OSError):
                os.fstat(p)
        spare = os.open(os.devnull, os.O_RDONLY)
        reused = os.dup2(spare, fd)  # another file under the port's old number
        os.close(spare)
        try:
            del port
            gc.collect()
            os.fstat(reused)  # still open: nobody closed it behind its owner's back
        finally:
            os.close(reused)
    finally:
        os.close(master)
