"""Wake-up pipes of the xfer threads (a leaf module): one byte in, all out."""

from __future__ import annotations

import os


def poke(fd: int) -> None:
    """One byte into the non-blocking pipe ``fd`` (a full pipe already holds one)."""
    try:
        os.write(fd, b"\x01")
    except BlockingIOError:
        pass


def drain(fd: int) -> None:
    """Empty the non-blocking pipe ``fd`` (what a wake-up left)."""
    try:
        os.read(fd, 64)
    except BlockingIOError:
        pass


__all__ = ["drain", "poke"]
