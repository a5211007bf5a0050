"""Serial ports for the master and the slave: opening, reading, writing, timing.

`open_port` takes a device path, any pyserial URL (``loop://``, ``socket://``,
``rfc2217://``...) or an already open pyserial object, and returns a `Port`.

* Formats a port refuses raise `PortError` naming the port and the setting.
  Linux pseudo-terminals carry no parity: depending on the kernel, setting
  even/odd parity fails with EINVAL or is silently dropped (PARENB cleared).
  Both are reported, because the format is read back after opening.
* On a POSIX port the hot path bypasses pyserial's read loop: ``select`` and
  ``os.read``/``os.write`` on its file descriptor (pyserial keeps it
  non-blocking).  Other ports go through pyserial's ``read``/``write``.
* `Port.write` returns when transmission actually ended: after the output
  drained (``tcdrain``), and never before the wire time of the bytes at the
  configured baud rate (USB adapters report "drained" while bytes are still
  in their FIFO).  Pseudo-terminals and network URLs have no wire: their
  transmission ends when the write returns.

RS-485 direction control: ``rs485`` is passed to pyserial as ``rs485_mode``
(``True`` for the default `serial.rs485.RS485Settings`).  On Linux that is the
kernel's RS-485 mode (TIOCSRS485), in which the driver switches the
transceiver itself, exactly at the end of the last stop bit.  Drivers without
it refuse the ioctl and the port is not opened (`PortError`).  pyserial's
user-space alternative, `serial.rs485.RS485` (RTS toggled around ``write``
with sleeps), cannot meet t3.5 turnaround at 19200 baud and above: the RTS
release depends on the scheduler, so the transceiver may cut the last byte
or hold the bus into the slave's answer; pass such an object as ``port`` if
the hardware has nothing better.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import time
from dataclasses import InitVar, dataclass, field
from typing import TYPE_CHECKING, Any

import serial
import serial.rs485

try:  # POSIX only: without it (Windows) every port takes pyserial's generic path
    import termios

    _TermiosError: type[Exception] = termios.error
    _HAVE_TERMIOS = True
except ImportError:
    _TermiosError = OSError
    _HAVE_TERMIOS = False

from pyrtu.core.line import BYTE_FORMAT, LINE_DEFAULTS, ByteFormat, LineConfig, check_keywords
from pyrtu.core.timing import bits_per_char
from pyrtu.drivers._portname import url_scheme
from pyrtu.pdu.errors import PortBusyError, PortError

if TYPE_CHECKING:  # Unpack is in typing from Python 3.11 (annotations only)
    from typing import Unpack

_READ_SIZE = 4096
_PTY_MAJORS = frozenset(range(136, 144)) | {2, 3}  # Unix98 pty slaves, legacy BSD ptys
_monotonic = time.monotonic


def _describe(baudrate: int, bytesize: int, parity: str, stopbits: float) -> str:
    stop = {1: "1", 1.5: "1.5", 2: "2"}.get(stopbits, str(stopbits))
    return f"{baudrate} baud {bytesize}{parity}{stop}"


def _is_pty(fd: int) -> bool:
    try:
        st = os.fstat(fd)
    except OSError:
        return False
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    return major in _PTY_MAJORS or (major == 5 and minor == 2)


def _posix_fd(ser: Any) -> int | None:
    if not _HAVE_TERMIOS:
        return None
    fd = getattr(ser, "fd", None)
    if not isinstance(fd, int) or fd < 0:
        return None
    try:
        os.fstat(fd)
        termios.tcgetattr(fd)
    except (OSError, _TermiosError):
        return None
    return fd


def failed(what: str, exc: BaseException) -> str:
    """``"<what> failed: <why>"``, said once: pyserial's own messages often begin
    with it already ("read failed: socket disconnected")."""
    text = str(exc)
    prefix = f"{what} failed: "
    return text if text.startswith(prefix) else prefix + text


def read_fd(port: Port, fd: int, readable: bool) -> bytes:
    """What the port's descriptor has now, in one read, without a poll first: pyserial
    keeps it non-blocking (VMIN = VTIME = 0), so no input is b"".  ``readable``: poll()
    said so, and then an empty read means the device is gone (`PortError`); errors as
    `Port.read`'s."""
    try:
        data = os.read(fd, _READ_SIZE)
    except BlockingIOError:
        return b""
    except OSError as exc:
        raise PortError(port.name, failed("read", exc)) from exc
    if not data and readable:
        raise PortError(port.name, "the device reports data but returns none (disconnected?)")
    return data


@dataclass(eq=False, repr=False)
class Port:
    """An open serial port with the few operations the master and slave need.

    ``ser``: the pyserial object (kept as ``serial``); ``owned``: opened here (so
    `close` closes it); ``baudrate`` .. ``bytesize``: the byte format it runs."""

    ser: InitVar[Any]
    name: str
    owned: bool
    baudrate: int
    parity: str = "N"
    stopbits: float = 1
    bytesize: int = 8
    serial: Any = field(init=False)

    def __post_init__(self, ser: Any) -> None:
        self.serial = ser
        self.char_time = bits_per_char(self.parity, self.stopbits, self.bytesize) / self.baudrate
        self.fd = _posix_fd(ser)
        if self.fd is not None:  # select.poll is POSIX only, as the fd path is
            self._poll = select.poll()
            self._poll.register(self.fd, select.POLLIN)
        self.is_pty = self.fd is not None and _is_pty(self.fd)
        #: a real line with wire timing (a tty that is not a pseudo-terminal)
        self.has_wire = self.fd is not None and not self.is_pty
        self.closed = False

    # ------------------------------------------------------------------ reading

    def read(self, timeout: float) -> bytes:
        """Bytes available within ``timeout`` seconds (b"" when none came)."""
        fd = self.fd
        if fd is None:
            return self._read_generic(timeout)
        if not self.readable(timeout):
            return b""
        return read_fd(self, fd, True)

    def readable(self, timeout: float) -> bool:
        """A port with a descriptor (``fd`` not None, POSIX): wait up to ``timeout``
        seconds for input with ``poll()`` (it rounds a fractional millisecond up:
        never early); True when there is some.  `PortError` when the wait fails."""
        try:
            return bool(self._poll.poll(timeout * 1000.0 if timeout > 0 else 0))
        except (OSError, ValueError) as exc:
            raise PortError(self.name, failed("read", exc)) from exc

    def _read_generic(self, timeout: float) -> bytes:
        ser = self.serial
        try:
            waiting = ser.in_waiting
            if waiting:
                return bytes(ser.read(waiting))
            if timeout <= 0:
                return b""
            if ser.timeout != timeout:
                ser.timeout = timeout
            data = bytes(ser.read(1))
            if data:
                waiting = ser.in_waiting
                if waiting:
                    data += bytes(ser.read(waiting))
            return data
        except (serial.SerialException, OSError) as exc:
            raise PortError(self.name, failed("read", exc)) from exc

    # ------------------------------------------------------------------ writing

    def write(self, data: bytes) -> tuple[float, float]:
        """Transmit ``data``; returns (start, end of transmission) on the monotonic clock."""
        start = _monotonic()
        fd = self.fd
        if fd is None:
            self._write_generic(data)
        else:
            n = self._write_some(fd, data)
            if n < len(data):
                self._write_rest(
                    fd, memoryview(data)[n:], start + 1.0 + len(data) * self.char_time * 2
                )
            if self.has_wire:
                try:
                    termios.tcdrain(fd)
                except termios.error as exc:
                    raise PortError(self.name, f"drain failed: {exc}") from exc
        end = _monotonic()
        if self.has_wire:
            end = max(end, start + len(data) * self.char_time)
        return start, end

    def _write_rest(self, fd: int, view: memoryview, deadline: float) -> None:
        """The output buffer was full (flow control, a slow line): wait and write on."""
        while view:
            left = deadline - _monotonic()
            if left <= 0:
                raise PortError(self.name, f"write timed out with {len(view)} bytes unsent")
            select.select((), (fd,), (), left)
            view = view[self._write_some(fd, view) :]

    def _write_some(self, fd: int, data: bytes | memoryview) -> int:
        """One non-blocking write: the bytes written (0 when the buffer is full)."""
        try:
            return os.write(fd, data)
        except BlockingIOError:
            return 0
        except OSError as exc:
            raise PortError(self.name, failed("write", exc)) from exc

    def _write_generic(self, data: bytes) -> None:
        try:
            self.serial.write(data)
            self.serial.flush()
        except (serial.SerialException, OSError) as exc:
            raise PortError(self.name, failed("write", exc)) from exc

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.owned:
            try:
                self.serial.close()
            except (serial.SerialException, OSError):  # already gone
                _forget(self.serial)


def _forget(ser: Any) -> None:
    """pyserial's close failed (its descriptor was already closed under it) and left
    the object open, holding the descriptor's number: its finalizer (io.IOBase's
    ``__del__``) would close that number again whenever it is collected, by then
    somebody else's file (an event loop's epoll or timer descriptor: uvloop aborts
    the process).  Mark it closed without touching that number, and close the POSIX
    ``Serial``'s abort pipes, which it closes only after the descriptor."""
    if getattr(ser, "fd", None) is not None:
        ser.fd = None
        for name in (
            "pipe_abort_read_w",
            "pipe_abort_read_r",
            "pipe_abort_write_w",
            "pipe_abort_write_r",
        ):
            fd = getattr(ser, name, None)
            if isinstance(fd, int):
                with contextlib.suppress(OSError):
                    os.close(fd)
                setattr(ser, name, None)
    with contextlib.suppress(Exception):
        ser.is_open = False


def _check_format(
    fd: int, name: str, fmt: str, parity: str, stopbits: float, bytesize: int
) -> None:
    """Read the format back: some drivers (ptys) drop settings without an error."""
    try:
        cflag = termios.tcgetattr(fd)[2]
    except termios.error as exc:
        raise PortError(name, f"cannot read the line settings back: {exc}") from exc
    if parity != "N" and not cflag & termios.PARENB:
        raise PortError(
            name,
            f"the port refused parity {parity} ({fmt}): the driver cleared PARENB "
            "(pseudo-terminals carry no parity; use parity='N')",
        )
    if parity == "N" and cflag & termios.PARENB:
        raise PortError(name, f"the port kept parity on although {fmt} was asked")
    if (stopbits == 2) != bool(cflag & termios.CSTOPB):
        raise PortError(name, f"the port refused {stopbits} stop bits ({fmt})")
    size = {7: termios.CS7, 8: termios.CS8}.get(bytesize)
    if size is not None and cflag & termios.CSIZE != size:
        raise PortError(name, f"the port refused {bytesize} data bits ({fmt})")


def _rs485_mode(rs485: Any) -> Any:
    """The pyserial RS-485 settings ``rs485`` asks for (None: leave the port's)."""
    if rs485 is None or rs485 is False:
        return None
    return serial.rs485.RS485Settings() if rs485 is True else rs485


def _adopt(
    port: Any, baudrate: int, parity: str, stopbits: float, bytesize: int, rs485: Any
) -> Port:
    """A serial object the caller opened (or will let us open); its own settings win."""
    if not (hasattr(port, "read") and hasattr(port, "write")):
        raise TypeError(f"port must be a path, a pyserial URL or a serial object, not {port!r}")
    name = str(getattr(port, "port", None) or getattr(port, "name", None) or repr(port))
    try:
        mode = _rs485_mode(rs485)
        if mode is not None:
            port.rs485_mode = mode
        if not getattr(port, "is_open", True):
            port.open()
    except ValueError as exc:
        raise PortError(name, f"the port refused RS-485 mode: {exc}") from exc
    except (serial.SerialException, OSError, _TermiosError) as exc:
        raise PortError(name, f"cannot open: {exc}") from exc
    baud = int(getattr(port, "baudrate", baudrate) or baudrate)
    p = str(getattr(port, "parity", parity) or parity).upper()[:1]
    sb = getattr(port, "stopbits", stopbits) or stopbits
    bs = getattr(port, "bytesize", bytesize) or bytesize
    return Port(port, name, False, baud, p, sb, bs)


def _open_error(exc: BaseException, port: str, fmt: str, parity: str, stopbits: float) -> PortError:
    """The `PortError` for a port pyserial could not open (what the OS said, in our words)."""
    # termios.error (not an OSError) escapes pyserial when tcsetattr refuses parity
    code = getattr(exc, "errno", None)
    if isinstance(exc, _TermiosError) and exc.args:
        code = exc.args[0]
    text = str(exc)
    if code in (errno.EWOULDBLOCK, errno.EAGAIN) and "exclusive" in text:
        return PortBusyError(port)
    if code == errno.EINVAL or "Invalid argument" in text:
        hint = " (pseudo-terminals carry no parity: use parity='N')" if parity != "N" else ""
        return PortError(
            port,
            f"the port refused the format {fmt}, parity {parity}, {stopbits} stop bit(s) "
            f"(EINVAL){hint}: {text}",
        )
    return PortError(port, f"cannot open: {text}")


def open_port(
    port: Any, *, rs485: Any = None, exclusive: bool = True, **byte_format: Unpack[ByteFormat]
) -> Port:
    """Open (or adopt) a serial port; PortError names the port and the setting.

    ``exclusive`` (POSIX): take an exclusive ``flock`` on the device, so that a
    second program opening it the same way (pyrtu, pyserial with
    ``exclusive=True``, ...) gets `PortBusyError` instead of splitting the
    bytes with the first; ``False`` shares the port.  The lock is advisory: a
    program that takes none is not stopped.  Adopted serial objects keep theirs.
    The byte format (``baudrate``, ``parity``, ``stopbits``, ``bytesize``) defaults
    to the line's (`pyrtu.core.line.LINE_DEFAULTS`: 19200 8E1).
    """
    check_keywords(byte_format, BYTE_FORMAT, "open_port")
    baudrate: int = byte_format.get("baudrate", LINE_DEFAULTS["baudrate"])
    parity: str = byte_format.get("parity", LINE_DEFAULTS["parity"])
    stopbits: float = byte_format.get("stopbits", LINE_DEFAULTS["stopbits"])
    bytesize: int = byte_format.get("bytesize", LINE_DEFAULTS["bytesize"])
    if not isinstance(port, str):
        return _adopt(port, baudrate, parity, stopbits, bytesize, rs485)
    url_scheme(port, own=())  # ValueError for a URL pyserial does not open
    parity = parity.upper()[:1]
    bits_per_char(parity, stopbits, bytesize)  # ValueError for a bad format
    fmt = _describe(baudrate, bytesize, parity, stopbits)
    mode = _rs485_mode(rs485)
    try:
        ser = serial.serial_for_url(port, do_not_open=True)
        ser.baudrate = baudrate
        ser.bytesize = bytesize
        ser.parity = parity
        ser.stopbits = stopbits
        ser.timeout = 0
        ser.write_timeout = None
        if os.name == "posix":
            ser.exclusive = bool(exclusive)
        if mode is not None:
            ser.rs485_mode = mode
        ser.open()
    except ValueError as exc:
        what = "RS-485 mode" if "RS485" in str(exc) else f"the format {fmt}"
        raise PortError(port, f"the port refused {what}: {exc}") from exc
    except (serial.SerialException, OSError, _TermiosError) as exc:
        raise _open_error(exc, port, fmt, parity, stopbits) from exc
    fd = _posix_fd(ser)
    if fd is not None:
        try:
            _check_format(fd, port, fmt, parity, stopbits, bytesize)
        except PortError:
            ser.close()
            raise
    return Port(ser, port, True, baudrate, parity, stopbits, bytesize)


__all__ = ["Port", "open_port"]


def open_line_port(port: Any, line: LineConfig, rs485: Any = None, exclusive: bool = True) -> Port:
    """`open_port` with the byte format of ``line`` (the drivers' one way to open)."""
    fmt: dict[str, Any] = {k: getattr(line, k) for k in BYTE_FORMAT}
    return open_port(port, rs485=rs485, exclusive=exclusive, **fmt)
