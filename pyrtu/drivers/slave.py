"""The Modbus slave (server) over a serial line, RTU or ASCII: the sync driver.

::

    store = pyrtu.DataStore()
    store.holding_registers.add_range(0, [0] * 100)
    with pyrtu.Slave("/dev/ttyUSB1", address=1, store=store, parity="E") as slave:
        slave.start()          # background thread; or slave.serve_forever()
        ...

Shared-bus behaviour: the framer (slave role) sizes every frame on the line,
requests and other slaves' responses alike, so a response is never taken for a
request.  The slave stays silent for other addresses, for frames with a bad
CRC/LRC, and for broadcasts (slave 0), which it executes when they are writes.
It answers no sooner than t3.5 after the end of the request (``t35=0``: no
wait) plus ``response_delay``.  With ``echo=True`` (an adapter that echoes)
the frame equal to what it just sent is dropped.

All of that is the sans-I/O server protocol (`pyrtu.protocol.ServerProtocol`); this
module only interprets its next action (`ServerProtocol.next_action`): `Reply`,
write it; `Listen` with ``needed``, sleep through the rest of a frame, not watching
the port, then read it; `Listen` until a time or `Idle`, wait in ``select`` on the
port's file descriptor and a wake-up pipe (`stop` writes to it).  For a request to
this slave the protocol sizes the nap to `PREPARE` before the end of the request
(its length from the rules) plus t3.5: the slave reads the rest, executes the
request, and writes the response at its time after one more short wait.  Three
wake-ups per transaction (the first byte, the request, the answer) instead of one
per byte (lenient mode; strict mode sees every gap); four for a request longer
than 8 bytes (a write of several registers or coils), whose length the first byte
cannot tell: the slave wakes once more when 8 bytes are in, rather than sleep
through the next request for the last one's length; and one more per half flush
timeout (25 ms) of a longer request (at 9600 baud, one of over 24 bytes), so that
the bytes read after a nap never hide or invent a silence the framer acts on.
The serving thread's timer slack is set to 1 µs (Linux) so that the answer's wait
ends on time.  The lock is held only while the protocol runs, never while waiting.
Ports without a file descriptor (pyserial URLs) are read with a 50 ms timeout,
which bounds `stop` there.

The diagnostic counters, event log and listen-only mode of the serial line
(FC 08, 11, 12) are per port (`pyrtu.protocol.diagnostics.LineState`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
from typing import TYPE_CHECKING, Any

from pyrtu.core._closing import Closing
from pyrtu.drivers._slack import swap_timer_slack
from pyrtu.drivers.port import read_fd
from pyrtu.drivers.slave_base import STANDARD_FUNCTIONS, Handler, PortSlave
from pyrtu.protocol.server import Listen, Reply, ServerAction

if TYPE_CHECKING:  # Unpack is in typing from Python 3.11 (annotations only)
    pass

log = logging.getLogger("pyrtu.drivers.slave")
_monotonic = time.monotonic

_POLL = 0.05  # ports without a file descriptor: the longest blocking read
#: wake this long before a response's time to prepare it (capped at half of t3.5 by the
#: protocol): the read, the function and the CRC take 50-300 µs on a loaded machine
PREPARE = 0.0005
#: the serving thread's timer slack (Linux), so that timed waits end on time (the
#: default 50 µs would add to every answer's turnaround)
_TIMER_SLACK_NS = 1000
_SELECT_LIMIT = 1024  # FD_SETSIZE


class Slave(PortSlave["Slave"], Closing):
    """A Modbus slave serving one or several addresses on one port."""

    _where = "Slave"

    def _driver_state(self) -> None:
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._serving = False
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        fd = self.port.fd
        #: the port and the wake-up pipe; the pipe alone (sleeping through a frame)
        self._wait_fds = [self._wake_r] if fd is None else [fd, self._wake_r]
        self._sleep_fds = [self._wake_r]

    def _guard(self) -> Any:
        return self._lock

    # ------------------------------------------------------------------ loop

    def serve_forever(self) -> None:
        """Serve requests until `stop` is called."""
        with self._lock:
            if self._serving:
                raise RuntimeError("this slave is already serving")
            self._serving = True
        slack = swap_timer_slack(_TIMER_SLACK_NS)
        try:
            action = self._next()
            while not self._stop.is_set():
                action = self._do(action, None)
        finally:
            if slack is not None:
                swap_timer_slack(slack)
            with self._lock:
                self.protocol.drop_response()
            self._serving = False
            self._drain_wake()

    def start(self) -> Slave:
        """Serve in a background (daemon) thread."""
        if self._thread is not None and self._thread.is_alive():
            raise RuntimeError("this slave is already started")
        self._stop.clear()
        self._drain_wake()
        self.error = None
        self._thread = threading.Thread(
            target=self._run, name=f"pyrtu-slave {self.port.name}", daemon=True
        )
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            self.serve_forever()
        except BaseException as exc:  # kept for the owner; the thread ends
            self.error = exc
            log.error("slave on %s stopped: %s", self.port.name, exc)

    def stop(self, timeout: float = 2.0) -> None:
        """Stop serving: the loop wakes at once (ports without a file descriptor: 50 ms)."""
        self._stop.set()
        with contextlib.suppress(OSError):  # full (a wake-up is pending) or closed
            os.write(self._wake_w, b"x")
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout)
            self._thread = None

    def close(self) -> None:
        self.stop()
        self.port.close()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def __repr__(self) -> str:
        return f"<pyrtu.Slave {sorted(self.addresses)} on {self.port.name} {self.mode}>"

    def poll(self, timeout: float = _POLL) -> None:
        """One step of the loop: wait up to ``timeout`` for bytes, act on what came; a
        request that began is read to its end and a response that became due is
        sent before returning (after its t3.5 and delay)."""
        action = self._do(self._next(), _monotonic() + timeout)
        while not self._stop.is_set():
            if isinstance(action, Listen) and not action.needed:
                with self._lock:
                    if self.protocol.pending is None:
                        return
            elif not isinstance(action, Reply | Listen):
                return
            action = self._do(action, None)

    # ------------------------------------------------------------------ the interpreter

    def _next(self) -> ServerAction:
        with self._lock:
            return self.protocol.next_action(_monotonic(), lead=PREPARE, nap=self._skip)

    def _do(self, action: ServerAction, until: float | None) -> ServerAction:
        """Carry out ``action`` (waiting no later than ``until``); the next action."""
        if isinstance(action, Reply):
            _start, end = self.port.write(action.data)
            with self._lock:
                self.protocol.transmitted(end)
        elif isinstance(action, Listen) and action.needed:
            # the rest of a frame the protocol sized: sleep through it, not watching the
            # port (only stop() wakes this), then read it all, even nothing
            timeout = action.until - _monotonic()
            if timeout > 0 and self._wait(self._sleep_fds, timeout) and self._woken():
                return action
            port = self.port
            assert port.fd is not None
            rest = read_fd(port, port.fd, False)
            with self._lock:
                self.protocol.receive_data(rest, _monotonic())
        else:
            at = action.until if isinstance(action, Listen) else None
            if until is not None and (at is None or until < at):
                at = until
            data = self._read(at, until is None)
            if data is None:
                return action  # stopped
            if data:
                with self._lock:
                    self.protocol.receive_data(data, _monotonic())
        return self._next()

    def _read(self, deadline: float | None, serving: bool) -> bytes | None:
        """The bytes that come by ``deadline`` (None: no limit; b"": none came); None
        when `stop` woke the wait.  Ports without a file descriptor: at most `_POLL`
        while ``serving`` (so that `stop` is seen)."""
        port = self.port
        fd = port.fd
        if fd is None:
            timeout = _POLL if deadline is None else max(0.0, deadline - _monotonic())
            return port.read(min(timeout, _POLL) if serving else timeout)
        wait = None if deadline is None else max(0.0, deadline - _monotonic())
        readable = False
        for ready in self._wait(self._wait_fds, wait):
            if ready != self._wake_r:
                readable = True
            elif self._woken():
                return None
        return read_fd(port, fd, True) if readable else b""

    def _woken(self) -> bool:
        """The wake-up pipe spoke: drained; True when it says stop."""
        self._drain_wake()
        return self._stop.is_set()

    @staticmethod
    def _wait(fds: list[int], timeout: float | None) -> list[int]:
        """The readable ones of ``fds`` within ``timeout`` seconds.  select() keeps the
        microseconds (poll and epoll round up to whole milliseconds: a t3.5 of 1.75 ms
        would become 2 and more); poll for descriptors past select's limit."""
        if max(fds) < _SELECT_LIMIT:
            return select.select(fds, (), (), timeout)[0]
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        return [fd for fd, _ in poller.poll(None if timeout is None else timeout * 1000.0)]

    def _drain_wake(self) -> None:
        with contextlib.suppress(OSError):
            while os.read(self._wake_r, 64):
                pass


__all__ = ["STANDARD_FUNCTIONS", "Handler", "Slave"]
