"""``--metrics HOST:PORT``: the option, its checks, and the server it opens.

Nothing here imports `prometheus_client`: a command without ``--metrics`` runs
without it, and one with ``--metrics`` but without the client says so (exit 2,
`MetricsError`) before it opens anything.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .server import MetricsServer

#: what ``--help`` says of the option
HELP = (
    "serve Prometheus metrics on http://HOST:PORT/metrics and a health check on "
    "/healthz (needs pip install 'pyrtu[metrics]'; docs/METRICS.md)"
)
#: how the extra is installed (the error names it)
EXTRA = "pip install 'pyrtu[metrics]' (prometheus_client)"


class MetricsError(ValueError):
    """A ``--metrics`` value that cannot be served (exit 2): malformed, a port in
    use, an address not on this host, the client library missing."""


def add_metrics_option(parser: argparse.ArgumentParser) -> None:
    """``--metrics HOST:PORT`` (checked by `open_metrics`, where an error is one line)."""
    parser.add_argument("--metrics", metavar="HOST:PORT", default=None, help=HELP)


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:9100`` for IPv6; port 1..65535) -> (host, port)."""
    host, sep, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise MetricsError(f"--metrics: IPv6 goes in brackets ([::1]:9100), not {text!r}")
    if not sep or not host or not port.isascii() or not port.isdigit():
        raise MetricsError(f"--metrics: expected HOST:PORT (127.0.0.1:9100), not {text!r}")
    number = int(port)
    if not 1 <= number <= 65535:
        raise MetricsError(f"--metrics: the port is 1..65535, not {number} ({text!r})")
    return host, number


def open_metrics(text: str | None, command: str) -> MetricsServer | None:
    """The metrics server of ``--metrics text``, bound (None without the option).
    `MetricsError` when the value is wrong, the port taken or the client missing."""
    if text is None:
        return None
    host, port = parse_address(text)
    try:
        import prometheus_client  # noqa: F401
    except ImportError:
        raise MetricsError(f"--metrics needs the Prometheus client: {EXTRA}") from None
    from .server import MetricsServer

    try:
        return MetricsServer(host, port, command)
    except OSError as exc:  # unknown host, port in use, an address not on this host
        where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        why = exc.strerror or str(exc)
        raise MetricsError(f"--metrics: cannot listen on {where}: {why}") from None


__all__ = ["EXTRA", "HELP", "MetricsError", "add_metrics_option", "open_metrics", "parse_address"]
