"""The version guard of the adapters: each states the versions it is tested with."""

from __future__ import annotations

import re
from importlib import metadata


class UnsupportedVersionError(ImportError):
    """The installed library is a version the adapter is not tested with."""


def parse_version(text: str) -> tuple[int, ...]:
    """The leading numeric release of a version string (``"3.16.1rc2"`` -> (3, 16, 1))."""
    m = re.match(r"\s*v?(\d+(?:\.\d+)*)", text)
    if m is None:
        raise ValueError(f"cannot read a version number from {text!r}")
    return tuple(int(part) for part in m.group(1).split("."))


#: The pymodbus releases pyrtu.compat.pymodbus is tested with: the latest of each minor
#: (3.13.1 is also what Home Assistant pins).  `make compat-matrix`
#: (tests/compat/matrix.py) runs the pymodbus compat tests in one virtual environment
#: per release; the main test environment has the last one.  docs/COMPAT.md lists them.
PYMODBUS_RELEASES: tuple[str, ...] = (
    "3.9.2",
    "3.10.0",
    "3.11.4",
    "3.12.1",
    "3.13.1",
    "3.14.0",
    "3.15.0",
    "3.16.1",
)


def _minors(releases: tuple[str, ...]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The range covering the minor versions of ``releases`` (consecutive minors)."""
    minors = sorted({parse_version(r)[:2] for r in releases})
    major, first = minors[0]
    if minors != [(major, m) for m in range(first, minors[-1][1] + 1)]:
        raise ValueError(f"the tested releases skip a minor version: {releases}")
    return (major, first, 0), (major, minors[-1][1] + 1)


#: distribution -> (lowest tested version, first version not tested): the ranges the
#: test suite runs (tests/compat/); any other version is refused.
TESTED: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "pymodbus": _minors(PYMODBUS_RELEASES),
    "minimalmodbus": ((2, 1, 0), (2, 2)),
    "umodbus": ((1, 0, 4), (1, 1)),
    "modbus_tk": ((1, 1, 5), (1, 2)),
}


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
