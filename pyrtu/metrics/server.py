"""The HTTP server of ``--metrics HOST:PORT``: ``/metrics`` and ``/healthz``.

The socket is bound when the command starts, before any port or broker is opened
(`MetricsServer.__init__`: OSError when it cannot be, which
`pyrtu.metrics.address.open_metrics` turns into a usage error naming ``--metrics``); the
server answers once the command runs (`MetricsServer.serve`), on threads of its own:

* ``/metrics``: the exposition of `prometheus_client` (the Prometheus text format,
  or OpenMetrics when the scraper asks for it), made of the command's `Source` and
  the process's own figures (CPU, memory, descriptors).  A source that cannot be
  read (the command's event loop does not answer within `LOOP_PATIENCE`) is a 503
  with the reason.
* ``/healthz``: 200 ``ok`` when the command's tasks run and its ports, listeners
  and broker are up; 503 with one reason per line otherwise.

The server's loop runs under `pyrtu.drivers.supervise` on an event loop thread of
its own (`pyrtu.drivers._loopthread.LoopThread`): if ``serve_forever`` raises, the
failure is logged and reported (``report``), and the server is started again on the
back-off.  A thread of its own keeps ``/healthz`` answering (503) when the command's
event loop is stuck.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import socket
import threading
from collections.abc import Callable, Iterable, Iterator
from socketserver import ThreadingMixIn
from typing import Any, Protocol
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from prometheus_client import CollectorRegistry, ProcessCollector, make_wsgi_app
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from pyrtu.drivers._loopthread import LoopThread
from pyrtu.drivers.reconnect import Backoff
from pyrtu.drivers.supervise import TaskFailure, supervise

log = logging.getLogger("pyrtu.metrics")

#: how long a scrape waits for the command's event loop to hand over its figures
LOOP_PATIENCE = 5.0
#: the paths of the health endpoint (the first is the documented one)
HEALTH_PATHS = ("/healthz", "/health")
#: the back-off of the HTTP server's task when it fails (seconds)
BACKOFF = Backoff(initial=0.5, maximum=30.0)

StartResponse = Callable[[str, list[tuple[str, str]]], Any]


class Unavailable(RuntimeError):
    """The command's figures cannot be read now (its loop stopped or is stuck)."""


class Source(Protocol):
    """What a command exposes: its metric families and its health."""

    def collect(self) -> Iterable[Metric]:
        """The metric families (on the HTTP server's thread; `Unavailable` when the
        command cannot be read)."""
        ...

    def health(self) -> list[str]:
        """What is wrong (empty: healthy); `Unavailable` when it cannot be told."""
        ...


def on_loop(loop: asyncio.AbstractEventLoop, function: Callable[[], Any]) -> Any:
    """``function()`` run on ``loop``'s thread (where the command's state changes),
    from another thread; `Unavailable` when the loop is closed or does not run it
    within `LOOP_PATIENCE`."""
    future: concurrent.futures.Future[Any] = concurrent.futures.Future()

    def run() -> None:
        if not future.set_running_or_notify_cancel():
            return
        try:
            future.set_result(function())
        except BaseException as exc:
            future.set_exception(exc)

    try:
        loop.call_soon_threadsafe(run)
    except RuntimeError:  # closed
        raise Unavailable("the command has stopped (its event loop is closed)") from None
    try:
        return future.result(LOOP_PATIENCE)
    except concurrent.futures.TimeoutError:
        future.cancel()
        raise Unavailable(
            f"the command's event loop did not answer within {LOOP_PATIENCE:g} s"
        ) from None


class _Quiet(WSGIRequestHandler):
    """No access log on stderr (the command's own output stays readable)."""

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("metrics: %s", format % args)


class _Server(ThreadingMixIn, WSGIServer):
    daemon_threads = True


class _Families(Collector):
    """The registry's view of the source, with ``pyrtu_info`` and ``pyrtu_healthy``."""

    def __init__(self, command: str, version: str) -> None:
        self.command, self.version = command, version
        self.source: Source | None = None

    def collect(self) -> Iterator[Metric]:
        source = self.source
        if source is None:
            raise Unavailable("the command is starting")
        info = GaugeMetricFamily(
            "pyrtu_info", "The command that serves these metrics", labels=["command", "version"]
        )
        info.add_metric([self.command, self.version], 1)
        yield info
        yield from source.collect()
        healthy = GaugeMetricFamily(
            "pyrtu_healthy", "1 when /healthz answers 200 (the command's tasks and ports are up)"
        )
        healthy.add_metric([], 0 if source.health() else 1)
        yield healthy


class MetricsServer:
    """``/metrics`` and ``/healthz`` on ``(host, port)`` for ``command`` (see the
    module docstring).  ``report``: told of each failure of the server's task."""

    def __init__(
        self,
        host: str,
        port: int,
        command: str,
        report: Callable[[TaskFailure], None] | None = None,
    ) -> None:
        from pyrtu._version import __version__

        self.command = command
        self._report = report
        self._families = _Families(command, __version__)
        self._registry = CollectorRegistry(auto_describe=False)
        self._registry.register(self._families)
        ProcessCollector(registry=self._registry)
        self._exposition = make_wsgi_app(self._registry)
        self._httpd = _bind(host, port, self._app)
        bound = self._httpd.server_address
        self.address: tuple[str, int] = (str(bound[0]), int(bound[1]))
        self._thread: LoopThread | None = None
        self._task: asyncio.Task[None] | None = None
        self._serving = False
        self._stopping = False

    # ---------------------------------------------------------------- life cycle

    def serve(self, source: Source) -> None:
        """Answer from now on, from ``source``."""
        self._families.source = source
        if self._thread is None:
            self._thread = LoopThread("pyrtu-metrics", self._begin, self._end)
            self._thread.start()

    def close(self) -> None:
        """Stop answering and release the socket (returns when the threads ended)."""
        self._stopping = True
        if self._thread is not None:
            self._thread.stop()
            self._thread = None
        self._httpd.server_close()

    async def _begin(self) -> None:
        self._task = supervise(
            "pyrtu-metrics-http",
            self._serve_forever,
            self._failed,
            backoff=BACKOFF,
            running=lambda: not self._stopping,
        )

    async def _end(self) -> None:
        if self._serving:
            self._httpd.shutdown()  # serve_forever returns within its poll interval
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass

    async def _serve_forever(self) -> None:
        """``serve_forever`` on a thread of its own; returns when it does (after
        `close`), raises what it raised."""
        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()

        def settle(error: BaseException | None) -> None:
            if done.done():
                return
            if error is None:
                done.set_result(None)
            else:
                done.set_exception(error)

        def main() -> None:
            error: BaseException | None = None
            try:
                self._httpd.serve_forever(poll_interval=0.1)
            except BaseException as exc:  # handed to the supervisor
                error = exc
            finally:
                self._serving = False
            try:
                loop.call_soon_threadsafe(settle, error)
            except RuntimeError:  # the loop closed meanwhile: nothing waits
                pass

        self._serving = True
        threading.Thread(target=main, name="pyrtu-metrics-http", daemon=True).start()
        await done

    def _failed(self, failure: TaskFailure) -> None:
        log.error(
            "metrics: task %s failed: %s (restarting in %.2f s)",
            failure.task,
            failure.cause,
            failure.retry_in,
        )
        if self._report is not None:
            try:
                self._report(failure)
            except Exception:
                log.exception("metrics: the report hook failed")

    # ---------------------------------------------------------------- HTTP

    def health(self) -> list[str]:
        """What is wrong (empty: healthy)."""
        source = self._families.source
        if source is None:
            return ["the command is starting"]
        try:
            return source.health()
        except Unavailable as exc:
            return [str(exc)]

    def _app(self, environ: dict[str, Any], start_response: StartResponse) -> Iterable[bytes]:
        path = environ.get("PATH_INFO") or "/"
        try:
            if path == "/metrics":
                try:
                    return self._exposition(environ, start_response)  # type: ignore[no-any-return]
                except Unavailable as exc:
                    return _text(start_response, "503 Service Unavailable", f"{exc}\n")
            if path in HEALTH_PATHS:
                problems = self.health()
                if problems:
                    body = "".join(f"{p}\n" for p in problems)
                    return _text(start_response, "503 Service Unavailable", body)
                return _text(start_response, "200 OK", "ok\n")
            if path == "/":
                body = f"pyrtu {self.command}: /metrics (Prometheus), /healthz (200 or 503)\n"
                return _text(start_response, "200 OK", body)
            return _text(start_response, "404 Not Found", f"no {path}: try /metrics or /healthz\n")
        except Exception as exc:  # a fault of pyrtu: the log has its trace, the client a 500
            log.exception("metrics: %s failed", path)
            return _text(start_response, "500 Internal Server Error", f"internal error: {exc}\n")


def _text(start_response: StartResponse, status: str, body: str) -> list[bytes]:
    data = body.encode()
    start_response(
        status, [("Content-Type", "text/plain; charset=utf-8"), ("Content-Length", str(len(data)))]
    )
    return [data]


def _bind(host: str, port: int, app: Callable[..., Iterable[bytes]]) -> _Server:
    """The server bound to ``(host, port)`` (OSError: unknown host, port in use...)."""
    family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]

    class Server(_Server):
        address_family = family

    return make_server(host, port, app, server_class=Server, handler_class=_Quiet)


__all__ = ["LOOP_PATIENCE", "MetricsServer", "Source", "Unavailable", "on_loop"]
