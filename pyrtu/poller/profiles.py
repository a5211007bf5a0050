"""The points of a device template of the registry (`pyrtu.devices.registry`), as
`Point` objects: the built-in drives' (cfw100, cfw320, cfw701, cv100, act, acu) and
any other template's."""

from __future__ import annotations

from pyrtu.devices.registry import builtin_names, find_template

from .config import template_points
from .points import Point

#: the built-in templates (the drives of the manuals)
PROFILES = builtin_names()


def profile_points(
    profile: str, name: str, bus: str, slave: int, interval: float = 1.0
) -> list[Point]:
    """The points of template ``profile`` (a registry name or a ``.toml`` file) at
    ``slave`` on ``bus``, named ``name.status``... and read every ``interval``
    seconds where the template gives no interval of its own."""
    points, _ = template_points(find_template(profile), name, bus, slave, interval)
    return points


def device_limits(profile: str) -> dict[str, int]:
    """The per-request limits of template ``profile`` (`Limits` keywords)."""
    return dict(find_template(profile).limits)


__all__ = ["PROFILES", "device_limits", "profile_points"]
