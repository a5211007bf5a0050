"""The backend, chosen once: the C core when it is built, else the pure-Python twin.

A leaf module (it imports only the two backends), so that any layer can reach the
active backend with ``from ._backend import active`` instead of importing the package
root.  ``PYRTU_PURE=1`` forces the twin; ``PYRTU_REQUIRE_C=1`` makes the import fail
when the C core is missing; without either, a missing C core is a `PureBackendWarning`
(an install that had no C compiler: docs/INSTALL.md).
"""

from __future__ import annotations

import os
import warnings
from types import ModuleType

from pyrtu.core import _pure
from pyrtu.core._errtypes import PureBackendWarning

#: why the twin runs without being asked for (PureBackendWarning's message)
NOT_BUILT = (
    "pyrtu: the C core is not built in this installation, so the pure-Python backend "
    "runs (pyrtu.BACKEND == 'python': the same results, the stream parser some 85x "
    "slower, no exchange thread). Install a pyrtu wheel, or reinstall with a C compiler "
    "(docs/INSTALL.md); PYRTU_PURE=1 chooses the pure-Python backend and silences this."
)


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
_PURE_ASKED = os.environ.get("PYRTU_PURE") == "1"
active: ModuleType = _pure if _PURE_ASKED or C is None else C
if C is None and not _PURE_ASKED:
    warnings.warn(NOT_BUILT, PureBackendWarning, stacklevel=2)


def describe() -> str:
    """The active backend in a few words (``pyrtu --version``)."""
    if active is C:
        return "backend c"
    if _PURE_ASKED:
        return "backend python, chosen by PYRTU_PURE=1"
    return "backend python: the C core is not built (docs/INSTALL.md)"


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
