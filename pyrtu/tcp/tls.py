"""The TLS of an ``mbaps://`` client (Modbus/TCP Security): the socket wrapped where it
is created, the server's certificate and host name verified by the caller's
`ssl.SSLContext` (``pyrtu.security.tls.client_context(cert, key, ca)``), and the TLS
session kept per (context, host, port) so that a reconnect resumes it: an abbreviated
handshake with no certificate exchange (`session_reused` says whether it did).

The asyncio client resumes through the same store: asyncio's ``create_connection``
takes no session, so the client hands it to `pyrtu.core._tls.FileContext.wrap_bio`
for the connect under way (`pyrtu.core._tls.resuming`; a context made otherwise
than by ``client_context`` runs full handshakes).  The sync client runs this path
only where the C core cannot (pyrtu/core/_tls.py: the C core over OpenSSL does the
handshake, keeps its own sessions and runs the transaction with the GIL released).
"""

from __future__ import annotations

import socket
import ssl
import weakref

from pyrtu.core import _tls as _ctls

#: the port of Modbus/TCP Security (IANA "mbap-s")
MBAPS_PORT = 802

_sessions: weakref.WeakKeyDictionary[ssl.SSLContext, dict[tuple[str, int], ssl.SSLSession]] = (
    weakref.WeakKeyDictionary()
)


def wrap(sock: socket.socket, context: ssl.SSLContext, host: str, port: int) -> ssl.SSLSocket:
    """``sock`` (connected, with its connect timeout) in TLS, its handshake done,
    resuming the session of the last connection to ``host:port`` with ``context``.
    `ssl.SSLError` (an OSError) when the handshake fails."""
    session = session_of(context, host, port)
    wrapped = context.wrap_socket(sock, server_hostname=host, session=session)
    remember(wrapped, context, host, port)
    return wrapped


def forget_sessions(context: ssl.SSLContext) -> None:
    """The sessions kept for ``context`` forgotten, on both paths (Python's ssl here, the
    C core's, pyrtu/core/_tls.py): the next connects run a full handshake."""
    _sessions.pop(context, None)
    _ctls.forget_sessions(context)


def session_of(context: ssl.SSLContext, host: str, port: int) -> ssl.SSLSession | None:
    """The session to resume on the next connection to ``host:port`` with ``context``."""
    return _sessions.get(context, {}).get((host, port))


def remember(
    sock: ssl.SSLSocket | ssl.SSLObject, context: ssl.SSLContext, host: str, port: int
) -> None:
    """Keep the connection's session for the next one (TLS 1.3 sends its tickets after
    the handshake: called again before the socket closes, it keeps the latest)."""
    session = sock.session
    if session is not None:
        _sessions.setdefault(context, {})[(host, port)] = session


__all__ = ["MBAPS_PORT", "forget_sessions", "remember", "session_of", "wrap"]
