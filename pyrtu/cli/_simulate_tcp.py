"""``pyrtu simulate ... --tcp HOST:PORT``: a simulated drive over Modbus TCP.

The drive's slave (the one on ``--port``, or one without a port when only ``--tcp``
is given: the drive's functions, handlers and identification over its DataStore)
served by `pyrtu.gateway.server.TcpServer` from an event loop in a thread of its own.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Any

from pyrtu.core.line import LINE_DEFAULTS, LineConfig
from pyrtu.drivers.slave_base import SlaveBase
from pyrtu.gateway.server import TcpServer

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

    def __init__(self, app: Any, host: str, port: int) -> None:
        self.loop = asyncio.new_event_loop()
        self.server = TcpServer(app)
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()
        try:
            asyncio.run_coroutine_threadsafe(self.server.start(host, port), self.loop).result(30)
        except BaseException:
            self.stop()
            raise

    @property
    def address(self) -> tuple[str, int]:
        assert self.server.address is not None
        return self.server.address

    def stop(self) -> None:
        if self.loop.is_closed():
            return
        if self.server.address is not None:
            asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(30)
        self.loop.close()
