"""``pyrtu simulate``: a warning when another device answers at the simulator's address.

Two simulators (or a simulator and a real drive) at one address on one bus both
answer every request to it; on RS-485 the answers collide and the master sees
garbage or nothing.  Nothing in the protocol says so, so the simulator listens:

* bytes that arrive while it is sending its own answer (a slave never hears
  itself: the drops of `pyrtu.vbus` and half-duplex adapters without echo do
  not give a transmitter its own bytes, and the master waits for the answer);
* a valid answer at one of its own addresses, to the function of the last
  request to them, that it did not send (the other device answered after it, with a longer
  response delay), seen by a monitor framer fed with what the slave reads.  Not
  for FC 05/06, whose answer is the request's echo: a monitor that did not hear
  this simulator's own answer takes the master's next write for an answer.

`ClashWatch` is sans-I/O (times are inputs); `watch_slave` puts it between a
slave (`pyrtu.Slave` or `AsyncSlave`) and its `ServerProtocol`, forwarding every
call unchanged.  It says so once per port (`ClashWatch.warning`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from pyrtu.core.ascii import make_framer
from pyrtu.core.frames import FrameKind
from pyrtu.core.line import LineConfig

__all__ = ["ClashWatch", "watch_slave"]

_ANSWERS = (FrameKind.RESPONSE, FrameKind.EXCEPTION)
_ECHOED = (5, 6)  # answers that repeat the request


class ClashWatch:
    """Whether another device answers at ``addresses`` on ``line`` (see the module doc)."""

    def __init__(self, addresses: Iterable[int], line: LineConfig) -> None:
        self.addresses = frozenset(addresses)
        self._framer = make_framer(line, "monitor")
        self._char = line.char_time
        self._tx: tuple[float, float] | None = None  # our last answer on the wire
        self._function: int | None = None  # of the last request to us (FC 05/06: None)
        # the pseudo-terminal's delivery runs up to ~0.1 ms ahead of the wire
        self._margin = max(2 * self._char, 200e-6)
        #: what was seen (None: nothing yet); set once
        self.warning: str | None = None

    def sending(self, adu: bytes, now: float) -> None:
        """The slave puts ``adu`` on the wire from ``now``."""
        self._tx = (now, now + len(adu) * self._char)

    def transmitted(self, end: float) -> None:
        """The slave's answer left the wire at ``end``."""
        if self._tx is not None:
            self._tx = (self._tx[0], max(self._tx[1], end))

    def received(self, data: bytes, now: float) -> str | None:
        """Bytes the slave read at ``now``; the warning when this is the first sign."""
        if not data or self.warning is not None:
            return None
        tx = self._tx
        # a character needs a character time on the wire: bytes read before our
        # answer's last character left began while we were sending
        if tx is not None and tx[0] + self._char <= now < tx[1] - self._margin:
            return self._warn("bytes came in while this simulator was sending its answer")
        self._framer.receive_data(data, now)
        while (frame := self._framer.next_event()) is not None:
            if frame.kind == FrameKind.REQUEST and frame.address in self.addresses:
                fc = frame.function
                self._function = None if fc is None or fc in _ECHOED else fc
            elif (
                frame.kind in _ANSWERS
                and frame.address in self.addresses
                and frame.function is not None
                and frame.function & 0x7F == self._function
            ):
                return self._warn(
                    f"an answer at address {frame.address} that this simulator did not send"
                )
        return None

    def _warn(self, what: str) -> str:
        self.warning = (
            f"another device answers at address {', '.join(map(str, sorted(self.addresses)))}"
            f" on this bus ({what}): the master gets garbled answers; give each one its own"
            " address"
        )
        return self.warning


class _Watched:
    """The slave's `ServerProtocol` with a `ClashWatch` listening to its calls."""

    def __init__(self, proto: Any, watch: ClashWatch, warn: Callable[[str], None]) -> None:
        self._proto = proto
        self._watch = watch
        self._warn = warn

    def receive_data(self, data: bytes, now: float) -> None:
        self._proto.receive_data(data, now)
        text = self._watch.received(bytes(data), now)
        if text is not None:
            self._warn(text)

    def next_action(self, now: float, **options: Any) -> Any:
        """The drivers' entry point: a `Reply` handed out is an answer being sent."""
        action = self._proto.next_action(now, **options)
        data = getattr(action, "data", None)
        if data is not None:
            self._watch.sending(data, now)
        return action

    def data_to_send(self, now: float) -> bytes | None:
        adu: bytes | None = self._proto.data_to_send(now)
        if adu is not None:
            self._watch.sending(adu, now)
        return adu

    def transmitted(self, end: float) -> None:
        self._proto.transmitted(end)
        self._watch.transmitted(end)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._proto, name)


def watch_slave(slave: Any, warn: Callable[[str], None]) -> ClashWatch:
    """Listen for another device at ``slave``'s addresses; ``warn(text)`` once."""
    watch = ClashWatch(slave.addresses, slave.line_config)
    slave.protocol = _Watched(slave.protocol, watch, warn)
    return watch
