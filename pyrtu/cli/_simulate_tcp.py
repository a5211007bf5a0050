"""``pyrtu simulate ... --tcp HOST:PORT``: a simulated drive over Modbus TCP.

The drive's slave (the one on ``--port``, or one without a port when only ``--tcp``
is given: the drive's functions, handlers and identification over its DataStore)
served by `pyrtu.tcp.server.TcpServer` from an event loop in a thread of its own.

Supervised: the server's tasks are the gateway's (restarted on the back-off, each
failure handed to ``on_task``); the thread itself ending while it should serve (its
loop stopped, or left by a ``SystemExit`` out of a callback) is `failure`, which the
command checks between its waits and ends on (exit 1, one line).
"""

from __future__ import annotations

import asyncio
import logging
import sys
import threading
from collections.abc import Callable
from typing import Any

from pyrtu.core.line import LINE_DEFAULTS, LineConfig
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.drivers.supervise import TaskFailure, cause
from pyrtu.security.tls import TlsListen
from pyrtu.tcp.server import TcpServer

log = logging.getLogger("pyrtu.cli")

#: `pyrtu.Slave` keywords that belong to the serial line (not to a TCP-only slave)
_LINE_KEYS = frozenset(LINE_DEFAULTS)


def tcp_only_slave(sim: Any, address: int) -> SlaveBase:
    """The drive's slave without a port (functions, handlers, identification)."""
    options = dict(sim.slave_options())
    for key in _LINE_KEYS & set(options):
        del options[key]  # frames are MBAP on TCP: no RTU lengths, no ASCII
    options.pop("response_delay", None)  # a turnaround of the serial line
    app = SlaveBase(address, sim.store, line=LineConfig(), **options)
    for fc, (handler, _req, _resp, broadcast) in sim.handlers().items():
        app.register_function(fc, handler, broadcast=broadcast)
    app.on_request(sim.telegram)
    with sim.lock:
        sim._served_at(address)
    return app


class TcpThread:
    """A `TcpServer` for ``app`` on its own event loop thread."""

    def __init__(
        self,
        app: Any,
        host: str,
        port: int,
        on_task: Callable[[TaskFailure], None] | None = None,
        tls: TlsListen | None = None,
        **security: Any,
    ) -> None:
        self.loop = asyncio.new_event_loop()
        self.loop.set_exception_handler(self._unhandled)
        # security: TcpServer's policy, audit and on_denied (pyrtu.cli._security)
        self.server = TcpServer(app, on_task=on_task, **security)
        self._stopping = False
        self._failure: BaseException | None = None
        self._thread = threading.Thread(target=self._main, name="pyrtu-simulate-tcp", daemon=True)
        self._thread.start()
        try:
            starting = self.server.start(host, port, tls=tls)
            asyncio.run_coroutine_threadsafe(starting, self.loop).result(30)
        except BaseException:
            self.stop()
            raise

    def _unhandled(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        """What the loop could give to no one (a connection's callback that raised;
        after the thread died, the tasks it left): one line on stderr while it
        serves, the log (``-v``) with the trace."""
        error = context.get("exception")
        text = str(context.get("message", "unhandled error"))
        if error is not None:
            text = f"{text}: {cause(error)}"
        log.debug("TCP server: %s", text, exc_info=error)
        if self._failure is None and not self._stopping:
            print(f"pyrtu simulate: TCP server: {text}", file=sys.stderr, flush=True)

    def _main(self) -> None:
        try:
            self.loop.run_forever()
        except BaseException as exc:  # SystemExit, KeyboardInterrupt out of a callback
            self._failure = exc
        else:
            if not self._stopping:
                self._failure = RuntimeError("its event loop stopped")

    @property
    def failure(self) -> BaseException | None:
        """Why the server's thread ended while it should serve (None: it serves)."""
        return None if self._thread.is_alive() else self._failure

    @property
    def address(self) -> tuple[str, int]:
        assert self.server.address is not None
        return self.server.address

    def stop(self) -> None:
        self._stopping = True
        if self.loop.is_closed():
            return
        if not self._thread.is_alive():  # it died: nothing runs the loop any more
            self.loop.close()
            return
        if self.server.address is not None:
            asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(30)
        self.loop.close()
