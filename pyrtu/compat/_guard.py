"""The version guard of the adapters: each states the versions it is tested with."""

from __future__ import annotations

import re
from importlib import metadata

#: distribution -> (lowest tested version, first version not tested): the ranges the
#: test suite runs (tests/test_compat_*.py); any other version is refused.
TESTED: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "pymodbus": ((3, 16, 0), (3, 17)),
    "minimalmodbus": ((2, 1, 0), (2, 2)),
    "umodbus": ((1, 0, 4), (1, 1)),
    "modbus_tk": ((1, 1, 5), (1, 2)),
}


class UnsupportedVersionError(ImportError):
    """The installed library is a version the adapter is not tested with."""


def parse_version(text: str) -> tuple[int, ...]:
    """The leading numeric release of a version string (``"3.16.1rc2"`` -> (3, 16, 1))."""
    m = re.match(r"\s*v?(\d+(?:\.\d+)*)", text)
    if m is None:
        raise ValueError(f"cannot read a version number from {text!r}")
    return tuple(int(part) for part in m.group(1).split("."))


def _dotted(version: tuple[int, ...]) -> str:
    return ".".join(str(v) for v in version)


def check_version(dist: str, installed: str) -> None:
    """Raise UnsupportedVersionError unless ``installed`` is in ``TESTED[dist]``."""
    low, high = TESTED[dist]
    version = parse_version(installed)
    if not low <= version < high:
        raise UnsupportedVersionError(
            f"pyrtu.compat.{dist} is tested with {dist} >= {_dotted(low)}, < {_dotted(high)}; "
            f"{dist} {installed} is installed (install a tested version, e.g. "
            f"pip install '{dist}>={_dotted(low)},<{_dotted(high)}')"
        )


def require(dist: str) -> str:
    """The installed version of ``dist``, checked; ImportError when it is missing."""
    try:
        installed = metadata.version(dist)
    except metadata.PackageNotFoundError:
        raise ImportError(
            f"pyrtu.compat.{dist} needs {dist}, which is not installed (pip install {dist})"
        ) from None
    check_version(dist, installed)
    return installed
