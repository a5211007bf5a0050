"""The errors of the master, the slave and the port layer.

Every error a transaction can end with derives from `ModbusError`:

* `ExceptionResponseError`: the slave answered with an exception response
  (Modbus Application Protocol V1.1b, section 7); ``.slave``, ``.function``,
  ``.code`` and ``.name``; ``.no_device_answered`` for 0x0A and 0x0B, which a
  gateway answers when the device behind it did not (a silent device, not an answer).
* `NoResponseError` (also a `TimeoutError`): nothing valid arrived in time.
* `FrameError` (also a `ValueError`): bad CRC/LRC, wrong slave, wrong function
  or malformed data; `BusFault` is the echo mismatch of an echoing adapter.
* `PortError` (also an `OSError`): a port is missing or refuses a format;
  `PortBusyError` when another program holds it.

`SlaveException` is raised by slave-side handlers to answer with an exception
code; it is not a `ModbusError` (nothing went wrong on the bus).
"""

from __future__ import annotations

from pyrtu.core._errtypes import ArgumentTypeError as ArgumentTypeError
from pyrtu.core._errtypes import PureBackendWarning as PureBackendWarning
from pyrtu.pdu.functions import FUNCTION_NAMES

#: Exception codes (Application Protocol V1.1b section 7; 7 from the serial-line
#: diagnostics, "NAK", counted by FC 08 sub-function 0x10).
EXCEPTION_NAMES: dict[int, str] = {
    1: "ILLEGAL FUNCTION",
    2: "ILLEGAL DATA ADDRESS",
    3: "ILLEGAL DATA VALUE",
    4: "SLAVE DEVICE FAILURE",
    5: "ACKNOWLEDGE",
    6: "SLAVE DEVICE BUSY",
    7: "NEGATIVE ACKNOWLEDGE",
    8: "MEMORY PARITY ERROR",
    10: "GATEWAY PATH UNAVAILABLE",
    11: "GATEWAY TARGET DEVICE FAILED TO RESPOND",
}

ILLEGAL_FUNCTION = 1
ILLEGAL_DATA_ADDRESS = 2
ILLEGAL_DATA_VALUE = 3
SLAVE_DEVICE_FAILURE = 4
ACKNOWLEDGE = 5
SLAVE_DEVICE_BUSY = 6
NEGATIVE_ACKNOWLEDGE = 7
MEMORY_PARITY_ERROR = 8
GATEWAY_PATH_UNAVAILABLE = 10
GATEWAY_TARGET_FAILED = 11

#: The exception codes a gateway answers for a device that did not: 0x0A, gateway
#: path unavailable (no path to the device's bus), and 0x0B, gateway target device
#: failed to respond (Application Protocol V1.1b section 7).  An answer carrying one
#: of them comes from the gateway, not from the device: the device did not answer.
NO_DEVICE_ANSWERED = frozenset({GATEWAY_PATH_UNAVAILABLE, GATEWAY_TARGET_FAILED})


def exception_name(code: int) -> str:
    """The name of an exception code (``"UNKNOWN EXCEPTION 0x..``" for others)."""
    return EXCEPTION_NAMES.get(code, f"UNKNOWN EXCEPTION 0x{code:02X}")


class ModbusError(Exception):
    """Base of every error a Modbus transaction can end with."""


class ExceptionResponseError(ModbusError):
    """The slave answered with an exception response (or a gateway in its name:
    `no_device_answered`)."""

    def __init__(self, slave: int, function: int, code: int) -> None:
        self.slave = slave
        self.function = function
        self.code = code
        self.name = exception_name(code)
        known = FUNCTION_NAMES.get(function)
        what = (
            f"{known} (function {function})" if known else f"function {function} (0x{function:02X})"
        )
        super().__init__(f"slave {slave} answered {what} with exception {code} ({self.name})")

    def __reduce__(self) -> tuple[type[ExceptionResponseError], tuple[int, int, int]]:
        return (type(self), (self.slave, self.function, self.code))

    @property
    def no_device_answered(self) -> bool:
        """True for exceptions 0x0A and 0x0B (`NO_DEVICE_ANSWERED`): a gateway answered
        because the device did not, so the device is as silent as after a timeout.
        Whatever decides "the slave answered" (the poller's slave health, a scan)
        asks this."""
        return self.code in NO_DEVICE_ANSWERED


class NoResponseError(ModbusError, TimeoutError):
    """No valid response arrived within the timeout."""

    def __init__(self, message: str, slave: int | None = None, function: int | None = None) -> None:
        super().__init__(message)
        self.slave = slave
        self.function = function


class FrameError(ModbusError, ValueError):
    """A response that cannot be the answer: bad CRC/LRC, wrong slave or function,
    malformed data."""

    def __init__(self, message: str, slave: int | None = None, function: int | None = None) -> None:
        super().__init__(message)
        self.slave = slave
        self.function = function


class BusFault(FrameError):
    """The bytes read back from an echoing adapter are not the bytes sent."""


class PortError(ModbusError, OSError):
    """A port cannot be opened, or refuses a setting; names the port and the setting."""

    def __init__(self, port: str, message: str) -> None:
        super().__init__(f"{port}: {message}")
        self.port = port


class PortBusyError(PortError):
    """Another program holds the port (it was opened exclusively).  ``advice`` is
    what the caller can do about it, in the caller's terms: the Python keyword by
    default; `with_advice` words it for another caller (a command-line flag, or
    none where the caller offers no way to share the port)."""

    #: the advice of `pyrtu.open_port`, `pyrtu.Master`, `pyrtu.Slave`
    PYTHON_ADVICE = "pass exclusive=False to share it"

    def __init__(self, port: str, advice: str | None = PYTHON_ADVICE) -> None:
        self.advice = advice
        how = f"; {advice}" if advice else ""
        super().__init__(
            port, f"busy: another program holds it (ports are opened exclusively{how})"
        )

    def with_advice(self, advice: str | None) -> PortBusyError:
        """The same error with ``advice`` (None: none), its cause kept."""
        out = PortBusyError(self.port, advice)
        out.__cause__ = self.__cause__
        return out

    def __reduce__(self) -> tuple[type[PortBusyError], tuple[str, str | None]]:
        return (type(self), (self.port, self.advice))


class SlaveException(Exception):
    """Raised by a slave handler (or a DataStore) to answer with exception ``code``."""

    def __init__(self, code: int, message: str = "") -> None:
        if isinstance(code, bool) or not isinstance(code, int) or not 1 <= code <= 255:
            raise ValueError(f"an exception code is 1..255, not {code!r}")
        self.code = code
        self.name = exception_name(code)
        super().__init__(message or f"exception {code} ({self.name})")


__all__ = [
    "EXCEPTION_NAMES",
    "NO_DEVICE_ANSWERED",
    "BusFault",
    "ExceptionResponseError",
    "FrameError",
    "ModbusError",
    "NoResponseError",
    "PortBusyError",
    "PortError",
    "PureBackendWarning",
    "SlaveException",
    "exception_name",
]
