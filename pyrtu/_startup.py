"""Ctrl-C while the ``pyrtu`` command starts ends it quietly, with status 130.

The command spends a noticeable time importing (the package, the C core, every
subcommand) before `pyrtu.cli.main` can catch anything; Python's own handler would
raise ``KeyboardInterrupt`` anywhere in those imports and print its traceback.
This module is the first that the package imports, so that from here on SIGINT
ends the command as it should: quietly, with the conventional status 128 + 2.
`pyrtu.cli.main` ends the start-up (`started`) when it runs the command, which
then has the ordinary behaviour (one-shot commands: status 130; the long-running
ones stop on SIGINT as their documentation says).

Only when this process is the ``pyrtu`` command (its script, or ``python -m
pyrtu``): a program that imports pyrtu keeps its own SIGINT handling.  What Python
runs before the package (its own start-up, ``site``) is beyond reach.
"""

from __future__ import annotations

import os
import signal
import sys
from types import FrameType

__all__ = ["EXIT_INTERRUPTED", "is_the_command", "started"]

#: 128 + SIGINT, what a shell reports for a command Ctrl-C ended
EXIT_INTERRUPTED = 130


def is_the_command() -> bool:
    """Whether this process runs the ``pyrtu`` command (not a program importing it)."""
    if not sys.argv:
        return False
    if sys.argv[0] == "-m":  # ``python -m MODULE`` while the module is being found
        argv = list(getattr(sys, "orig_argv", []))
        return "-m" in argv and argv[argv.index("-m") + 1 :][:1] == ["pyrtu"]
    name = os.path.basename(sys.argv[0])
    return name.removesuffix(".exe") == "pyrtu"


def _interrupted(signum: int, frame: FrameType | None) -> None:
    """End the process at once, status 130.  Not by raising: Python runs a signal
    handler between any two bytecodes, also inside a weakref callback or a
    ``__del__`` (the import system's module locks have one), where an exception is
    printed and then ignored, and the command would go on.  Nothing is open yet (the
    command has not started); what was written is flushed first."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    os._exit(EXIT_INTERRUPTED)


def started() -> None:
    """The start-up is over: SIGINT gets Python's default handler back (if this module
    had replaced it; a handler installed since is left alone)."""
    try:
        if signal.getsignal(signal.SIGINT) is _interrupted:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    except ValueError:  # not the main thread: signals are not ours to set
        pass


def _install() -> None:
    try:
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            signal.signal(signal.SIGINT, _interrupted)
    except ValueError:  # imported from another thread than the main one
        pass


if is_the_command():
    _install()
