"""`AsyncSlave`: the Modbus slave on asyncio (re-exported by `pyrtu.drivers.aio`).

Same keywords as `pyrtu.Slave`, same protocol underneath (`pyrtu.protocol.server`); many
slaves (ports) share one event loop and one thread::

    async def main():
        slaves = [AsyncSlave(path, address=1, store=store, parity="N") for path in paths]
        async with asyncio.TaskGroup() as tg:
            for s in slaves:
                tg.create_task(s.serve())

The driver interprets the protocol's next action (`ServerProtocol.next_action`):
`Reply` is written when due (on a descriptor: handed out ahead, written at its time
by the port's xfer thread), `Listen` is a timer at its ``until`` (with
``needed``: the reader set aside until then), `Idle` no timer.  A port with a file
descriptor is watched with ``loop.add_reader``; timers are those of
`pyrtu.drivers._ptimer` (the loop's own on `pyrtu.drivers.aio.run`'s loop, a timerfd on
loops whose timers are whole milliseconds: asyncio's epoll loop, uvloop).
When the first bytes of a frame come, the reader is set aside until the protocol's
`wake_at` (for a request to this slave: `_LEAD`, 1 ms, before the end of its t3.5,
at most half of it): the rest is read and the request executed in that wake-up
(lenient mode), and the response goes to the port's xfer thread (the backend's
`AsyncXferRunner`, `pyrtu.drivers.xfer`: a C thread without the GIL), which writes it
at its time to the microsecond whatever the loop is doing (the last `_SPIN` of the
wait on the clock); the loop wakes once more when it is written.
Three wake-ups per transaction, four for a request longer than 8 bytes (its length
is known once 8 bytes are in), and one more per 25 ms of a longer one (see
`pyrtu.drivers.slave`).  A port without a file descriptor (a pyserial URL) is read by
a worker thread with pyserial's generic reads, which hands the bytes to the loop;
its responses are written when due.

A port that fails (unplugged) ends `serve` with the `PortError`; the port is
closed, its reader removed, and the other slaves of the loop go on.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from typing import TYPE_CHECKING, Any

from pyrtu.core._closing import AsyncClosing
from pyrtu.drivers import _ptimer, xfer, xfer_runners
from pyrtu.drivers.port import read_fd
from pyrtu.drivers.slave import PREPARE
from pyrtu.drivers.slave_base import PortSlave
from pyrtu.pdu.errors import PortError
from pyrtu.protocol.client_actions import Xfer
from pyrtu.protocol.server import Listen, Reply

if TYPE_CHECKING:  # Unpack is in typing from Python 3.11 (annotations only)
    pass

log = logging.getLogger("pyrtu.drivers.slave")

_POLL = 0.05  # the reader thread of a port without a file descriptor
#: the nap ends this long before a response's time (the protocol caps it at half the
#: turnaround, so that the request is in): the rest of the request read, the response
#: made and handed to the xfer thread before its time.  Twice the sync `Slave`'s
#: `PREPARE`: one loop serves many ports, and a nap on it wakes later (with 0.5 ms, 18 %
#: of the responses of four simulated drives on one loop were handed over late, 5 %
#: with 1 ms; 4 buses at 115200, 2-vCPU VM, 2026-11-27)
_LEAD = 2 * PREPARE
#: a response is handed to the port's xfer thread up to this long before its time
#: (the thread writes it then; see `_after`)
_AHEAD = 2 * _LEAD
#: the xfer thread waits out the last of a response's turnaround on the clock
#: (`pyrtu.drivers.xfer.XferPlan.spin`): asleep, it wakes about 50 µs late (p90 94 µs
#: on an idle 2-vCPU VM, 2026-11-27), and the response with it
_SPIN = 100e-6


class AsyncSlave(PortSlave["AsyncSlave"], AsyncClosing):
    """A Modbus slave on asyncio, serving one or several addresses on one port."""

    _where = "AsyncSlave"

    def _driver_state(self) -> None:
        self._loop: asyncio.AbstractEventLoop | None = None
        self._done: asyncio.Future[None] | None = None
        self._task: asyncio.Task[None] | None = None
        self._timer: asyncio.TimerHandle | _ptimer.TimerHandle | None = None
        self._timer_at: float | None = None
        self._reading = False  # the reader is installed (not set aside for a frame)
        self._resume_at: float | None = None  # when a set-aside reader comes back
        self._out: memoryview | None = None  # the unwritten rest of a response
        self._thread: threading.Thread | None = None
        self._thread_stop = threading.Event()
        #: the port's xfer thread (the backend's AsyncXferRunner): a response
        #: written at its time, to the microsecond, whatever the loop is doing
        self._ax: xfer.AsyncXferRunner | None = None
        self._ax_loop: asyncio.AbstractEventLoop | None = None
        self._replying = False  # a response is with the xfer thread

    def _guard(self) -> Any:
        return contextlib.nullcontext()  # one thread: the loop's

    # ------------------------------------------------------------------ serving

    async def serve(self) -> None:
        """Serve until `stop` (or cancellation); a failing port raises `PortError`."""
        if self._done is not None:
            raise RuntimeError("this slave is already serving")
        if self.port.closed:
            raise PortError(self.port.name, "the port is closed")
        loop = asyncio.get_running_loop()
        self._loop = loop
        done = self._done = loop.create_future()
        self.error = None
        try:
            if self.port.fd is not None:
                self._add_reader()
            else:
                self._thread_stop.clear()
                self._thread = threading.Thread(
                    target=self._read_thread, name=f"pyrtu-aslave {self.port.name}", daemon=True
                )
                self._thread.start()
            self._after(loop.time())
            await done
        finally:
            if self._done is done:  # not already torn down by `stop`
                self._teardown()

    def start(self) -> asyncio.Task[None]:
        """Serve in a task of the running loop; returns it."""
        if self._task is not None and not self._task.done():
            raise RuntimeError("this slave is already started")
        self._task = asyncio.get_running_loop().create_task(self.serve())
        return self._task

    async def stop(self) -> None:
        """Stop serving (at once; the task of `start` ends).  The port is off the
        loop when this returns, even if `serve` runs in a task of the caller's that
        has not resumed yet, so `close` never closes a descriptor the loop watches."""
        done = self._done
        if done is not None and not done.done():
            done.set_result(None)
            self._teardown()
        task = self._task
        if task is not None:
            self._task = None
            with contextlib.suppress(PortError, asyncio.CancelledError):
                await task

    async def close(self) -> None:
        await self.stop()
        self.port.close()

    def __repr__(self) -> str:
        return f"<pyrtu.AsyncSlave {sorted(self.addresses)} on {self.port.name} {self.mode}>"

    def _teardown(self) -> None:
        self.protocol.drop_response()
        self._close_xfer_runner()
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self._timer_at = None
        self._remove_reader()
        if self._out is not None and self.port.fd is not None and self._loop is not None:
            self._loop.remove_writer(self.port.fd)
        self._out = None
        self._resume_at = None
        thread, self._thread = self._thread, None
        if thread is not None:
            self._thread_stop.set()
            thread.join(2 * _POLL + 1.0)
        self._done = None

    def _fail(self, exc: BaseException) -> None:
        """The port failed: end `serve` with the error, close the port (no fd left)."""
        log.error("slave on %s stopped: %s", self.port.name, exc)
        self.error = exc
        self._close_xfer_runner()
        self._remove_reader()
        if self._out is not None and self._loop is not None and self.port.fd is not None:
            self._loop.remove_writer(self.port.fd)
            self._out = None
        self.port.close()
        if self._done is not None and not self._done.done():
            self._done.set_exception(exc)

    # ------------------------------------------------------------------ reading

    def _add_reader(self) -> None:
        fd = self.port.fd
        if not self._reading and fd is not None and self._loop is not None:
            self._loop.add_reader(fd, self._on_readable)
            self._reading = True

    def _remove_reader(self) -> None:
        fd = self.port.fd
        if self._reading and fd is not None and self._loop is not None:
            self._loop.remove_reader(fd)
        self._reading = False

    def _on_readable(self) -> None:
        self._read_now(True, False)

    def _read_now(self, readable: bool, napped: bool) -> None:
        assert self._loop is not None and self.port.fd is not None
        try:
            data = read_fd(self.port, self.port.fd, readable)
        except PortError as exc:
            self._fail(exc)
            return
        now = self._loop.time()
        if data or napped:
            self.protocol.receive_data(data, now)  # after a nap even nothing: it ends it
        self._after(now)

    def _read_thread(self) -> None:
        """A port without a file descriptor: pyserial's reads, bytes to the loop."""
        loop = self._loop
        assert loop is not None
        while not self._thread_stop.is_set():
            try:
                data = self.port.read(_POLL)
            except PortError as exc:
                with contextlib.suppress(RuntimeError):  # the loop is closed
                    loop.call_soon_threadsafe(self._fail, exc)
                return
            if data:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(self._on_data, data)

    def _on_data(self, data: bytes) -> None:
        if self._done is None or self._loop is None:
            return
        now = self._loop.time()
        self.protocol.receive_data(data, now)
        self._after(now)  # (no nap: the reader thread reads on its own)

    # ------------------------------------------------------------- time, sending

    def _after(self, now: float) -> None:
        """The protocol saw bytes or time: carry out its actions, up to the next wait.

        On a descriptor the nap ends `_LEAD` before a response's time (the rest of
        the request read, the response made meanwhile) and the response goes to the
        port's xfer thread, which writes it at its time; elsewhere it is written
        when due."""
        if self._out is not None or self._replying or self._done is None or self._done.done():
            return  # a response is being written: its end comes back here
        proto = self.protocol
        nap = self._skip and self._reading
        fd = self.port.fd
        lead, ahead = (_LEAD, _AHEAD) if fd is not None else (0.0, 0.0)
        action = proto.next_action(now, nap=nap, lead=lead, ahead=ahead)
        while isinstance(action, Reply):
            if action.at > now and fd is not None:
                self._reply_at(fd, action)
                return  # its end comes back through _replied
            if not self._write(action.data, now):
                return  # written in part (the writer goes on) or the port failed
            action = proto.next_action(now, nap=nap, lead=lead, ahead=ahead)
        if self._done is None or self._done.done():
            return
        at = None
        if isinstance(action, Listen):
            at = action.until
            if action.needed:
                # the rest of a frame the protocol sized (and the answer's time): one
                # wake-up for all of it, with the reader set aside; the framer's silence
                # timer counts from the last byte read, which says nothing meanwhile
                self._remove_reader()
                self._resume_at = at
        self._rearm(at)

    def _rearm(self, at: float | None) -> None:
        assert self._loop is not None
        if at == self._timer_at:
            return
        if self._timer is not None:
            self._timer.cancel()
        self._timer_at = at
        self._timer = None if at is None else _ptimer.call_at(self._loop, at, self._on_timer)

    def _on_timer(self) -> None:
        assert self._loop is not None
        self._timer = self._timer_at = None
        if self._resume_at is not None:
            self._resume_at = None
            self._add_reader()
            self._read_now(False, True)  # what came while the reader was set aside
            return
        self._after(self._loop.time())

    def _reply_at(self, fd: int, action: Reply) -> None:
        """Hand a response to the port's xfer thread, to be written at its time."""
        loop = self._loop
        assert loop is not None
        ax = self._ax
        if ax is None:
            ax = self._ax = xfer_runners.async_xfer_runner(self.protocol.backend)
        port = self.port
        ax.submit(
            xfer.XferPlan(
                fd,
                port.has_wire,
                port.char_time,
                Xfer(action.data, action.at, 0.0, 0.0, 0, 0),
                look=False,
                spin=_SPIN,
            )
        )
        self._replying = True
        if self._ax_loop is not loop:
            loop.add_reader(ax.fd, self._replied)
            self._ax_loop = loop

    def _replied(self) -> None:
        ax, loop = self._ax, self._loop
        if ax is None or loop is None or (r := ax.result()) is None:
            return
        self._replying = False
        if r.status == xfer.ERRNO:
            self._fail(
                PortError(self.port.name, f"write failed: {OSError(r.err, os.strerror(r.err))}")
            )
            return
        if r.sent:
            self.protocol.transmitted(r.end)
        self._after(loop.time())

    def _close_xfer_runner(self) -> None:
        """The xfer thread ends (a response it holds is cancelled: never sent
        late), before the port can close under it."""
        ax, self._ax = self._ax, None
        self._replying = False
        if ax is None:
            return
        if self._ax_loop is not None and not self._ax_loop.is_closed():
            self._ax_loop.remove_reader(ax.fd)
        self._ax_loop = None
        ax.close()

    def _write(self, adu: bytes, now: float) -> bool:
        port = self.port
        fd = port.fd
        if fd is None:
            try:
                _start, end = port.write(adu)  # pyserial's write: URL ports have no wire
            except PortError as exc:
                self._fail(exc)
                return False
            self.protocol.transmitted(end)
            return True
        try:
            n = os.write(fd, adu)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self._fail(PortError(port.name, f"write failed: {exc}"))
            return False
        # a real line: the bytes leave the wire one character time each after now
        end = now + len(adu) * port.char_time if port.has_wire else now
        if n == len(adu):
            self.protocol.transmitted(end)
            return True
        self._out = memoryview(adu)[n:]
        self._out_end = end
        assert self._loop is not None
        self._loop.add_writer(fd, self._on_writable)
        return False

    def _on_writable(self) -> None:
        fd = self.port.fd
        out = self._out
        if fd is None or out is None or self._loop is None:
            return
        try:
            n = os.write(fd, out)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(PortError(self.port.name, f"write failed: {exc}"))
            return
        self._out = out[n:]
        if not self._out:
            self._out = None
            self._loop.remove_writer(fd)
            now = self._loop.time()
            self.protocol.transmitted(max(self._out_end, now))
            self._after(now)


__all__ = ["AsyncSlave"]
