"""Deprecated path: `pyrtu.timing` (character and silence times).  Each name used here warns
(`DeprecationWarning`) naming its one public path: ``import pyrtu``'s own name
(`_ROOT`), else `pyrtu.core.timing`."""

from __future__ import annotations

from pyrtu.core._deprecated import renamed

#: the names `import pyrtu` has
_ROOT = ("Timing",)
#: the names only pyrtu.core.timing has
_HOME = (
    "BYTESIZES",
    "MAX_BAUDRATE",
    "MIN_BAUDRATE",
    "MODES",
    "PARITIES",
    "STOPBITS",
    "TIMING_RULES",
    "apply_overrides",
    "bits_per_char",
    "check_baudrate",
    "check_bytesize",
    "check_mode",
    "check_parity",
    "check_stopbits",
    "check_timing",
    "compute_timing",
    "positive_seconds",
    "seconds_to_us",
)

__getattr__ = renamed(
    __name__,
    {
        **{name: ("pyrtu", name) for name in _ROOT},
        **{name: ("pyrtu.core.timing", name) for name in _HOME},
    },
)
__all__ = [*_ROOT, *_HOME]
