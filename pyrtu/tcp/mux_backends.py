"""The mux of a backend (`pyrtu.tcp.mux` has the contract): C (pyrtu/tcp/_cmux.py
over csrc/rtu_mux_io.c) where the core is built with epoll, else the twin
(pyrtu/tcp/_pymux.py), chosen here, once per mux."""

from __future__ import annotations

import functools

from pyrtu.core._backend import backend
from pyrtu.tcp.mux import TcpMux


@functools.cache
def available(name: str | None = None) -> bool:
    """Whether backend ``name`` (None: the active one) has a mux here: C where
    there is ``epoll`` (Linux), the twin where the selector has a descriptor
    (epoll, kqueue; not a select() one)."""
    be = backend(name)
    if be.BACKEND == "c":
        from pyrtu.tcp import _cmux

        if _cmux.supported():
            return True
    from pyrtu.tcp import _pymux

    return _pymux.supported()


def open_mux(capacity: int, name: str | None = None) -> TcpMux:
    """A `TcpMux` of ``capacity`` connections on backend ``name`` (None: the active
    one; the twin where the C core has no mux here)."""
    if not isinstance(capacity, int) or isinstance(capacity, bool) or not 1 <= capacity <= 65536:
        raise ValueError(f"capacity must be 1..65536 connections, not {capacity!r}")
    be = backend(name)
    if be.BACKEND == "c":
        from pyrtu.tcp import _cmux

        if _cmux.supported():
            return _cmux.CMux(capacity)
        if name == "c":
            raise ValueError("backend c has no mux on this platform (it needs epoll)")
    from pyrtu.tcp import _pymux

    return _pymux.PyMux(capacity)


__all__ = ["available", "open_mux"]
