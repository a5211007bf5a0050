"""Standard points of the drive profiles of `pyrtu.devices`, as `Point` objects."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from ..devices import bonfiglioli, cv100, weg
from .points import Point

_MODULES: Mapping[str, Any] = {
    "cfw100": weg,
    "cfw320": weg,
    "cfw701": weg,
    "cv100": cv100,
    "act": bonfiglioli,
    "acu": bonfiglioli,
}
PROFILES = tuple(_MODULES)


def _module(profile: object) -> Any:
    if not isinstance(profile, str) or profile.lower() not in _MODULES:
        raise ValueError(f"profile: must be one of {', '.join(_MODULES)}, not {profile!r}")
    return _MODULES[profile.lower()]


def profile_points(
    profile: str, name: str, bus: str, slave: int, interval: float = 1.0
) -> list[Point]:
    """The standard points (status, speed, current, fault where the drive has them
    as 16-bit registers) of drive ``profile`` at ``slave`` on ``bus``, named
    ``name.status``..."""
    make: Callable[..., list[dict[str, Any]]] = _module(profile).poll_points
    return [Point(bus=bus, slave=slave, **kw) for kw in make(name, interval)]


def device_limits(profile: str) -> dict[str, int]:
    """The per-request limits of drive ``profile`` (`Limits` keywords)."""
    return dict(_module(profile).POLL_LIMITS)


__all__ = ["PROFILES", "device_limits", "profile_points"]
