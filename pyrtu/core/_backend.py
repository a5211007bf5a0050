"""The backend, chosen once: the C core when it is built, else the pure-Python twin.

A leaf module (it imports only the two backends), so that any layer can reach the
active backend with ``from ._backend import active`` instead of importing the package
root.  ``PYRTU_PURE=1`` forces the twin; ``PYRTU_REQUIRE_C=1`` makes the import fail
when the C core is missing.
"""

from __future__ import annotations

import os
from types import ModuleType

from pyrtu.core import _pure


def _load_c() -> ModuleType | None:
    try:
        from pyrtu.core import _cext
    except ImportError as exc:
        if os.environ.get("PYRTU_REQUIRE_C") == "1":
            raise ImportError(
                f"PYRTU_REQUIRE_C=1 but the pyrtu C core is not built ({exc}); "
                "reinstall with a C compiler (pip install .)"
            ) from exc
        return None
    return _cext


C: ModuleType | None = _load_c()
active: ModuleType = _pure if os.environ.get("PYRTU_PURE") == "1" or C is None else C


def backend(name: str | None = None) -> ModuleType:
    """The backend module named ``"c"`` or ``"python"`` (None: the active one)."""
    if name is None:
        return active
    if name == "python":
        return _pure
    if name == "c":
        if C is None:
            raise ImportError("the pyrtu C core is not built")
        return C
    raise ValueError(f"backend must be 'c' or 'python', not {name!r}")


def available_backends() -> tuple[str, ...]:
    """The backends that can run here."""
    return ("c", "python") if C is not None else ("python",)
