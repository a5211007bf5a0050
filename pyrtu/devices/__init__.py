"""The drives of the seed manuals: profiles (master side) and simulators (slave side).

=============  ====================  ===========================  =================
manufacturer   module                profiles                     simulators
=============  ====================  ===========================  =================
WEG            `weg`, `weg_sim`      `CFW100`, `CFW320`,          `CFW100Simulator`,
                                     `CFW701`                     `CFW320Simulator`,
                                                                  `CFW701Simulator`
CV100/FV100    `cv100`, `cv100_sim`  `CV100`                      `CV100Simulator`
Bonfiglioli    `bonfiglioli`,        `ACT`, `ACU`                 `ACTSimulator`,
               `bonfiglioli_sim`                                  `ACUSimulator`
=============  ====================  ===========================  =================

A profile wraps a `pyrtu.Master`::

    drive = CFW701(master, address=1)
    drive.start(); drive.set_speed_hz(30)

A simulator is a drive model behind a `pyrtu.DataStore`, served by a `pyrtu.Slave`::

    sim = CFW701Simulator()
    sim.serve("/dev/pts/5", address=1, parity="N")   # background thread

Each drive is a template of the registry (`registry`, templates/*.toml): its points,
limits and identity as data, and hooks to the code data cannot say (its profile
class, its simulator, `describe_register`).  `SIMULATORS`/`PROFILES` map the
built-in templates' names (cfw100, cfw320, cfw701, cv100, act, acu) to the classes;
`describe_register` names a register value in the manual's terms (for monitors).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from . import bonfiglioli, cv100, weg
from ._simbase import DriveSimulator
from .bonfiglioli import ACT, ACU, DriveState, Vectron, VectronStatus
from .bonfiglioli_sim import ACTSimulator, ACUSimulator, VectronSimulator
from .cv100 import CV100, CV100Status
from .cv100_sim import CV100Simulator
from .motor import ManualClock, Motor, Supervision
from .registry import Template, TemplateError, entries, find_template
from .weg import (
    CFW100,
    CFW320,
    CFW701,
    ErrorAction,
    InterfaceStatus,
    WegControl,
    WegDrive,
    WegStatus,
)
from .weg_sim import CFW100Simulator, CFW320Simulator, CFW701Simulator, WegSimulator


def _builtin() -> list[Template]:
    return [entry.load() for entry in entries({}).values()]


_BUILTIN = _builtin()
#: the built-in templates' simulators, profiles, example addresses and ASCII
#: capability (`pyrtu.devices.registry` is the one list: templates/*.toml)
SIMULATORS: Mapping[str, type[DriveSimulator]] = {
    t.name: t.hook("simulator") for t in _BUILTIN if "simulator" in t.hooks
}
PROFILES: Mapping[str, type[Any]] = {
    t.name: t.hook("profile") for t in _BUILTIN if "profile" in t.hooks
}
#: the address the manual's examples use (a simulator's natural default)
EXAMPLE_ADDRESS: Mapping[str, int] = {t.name: t.address for t in _BUILTIN}
#: which devices speak ASCII as well as RTU
ASCII_DEVICES = frozenset(t.name for t in _BUILTIN if "ascii" in t.modes)


def simulator(device: str, **options: Any) -> DriveSimulator:
    """A drive simulator by template name (``"cfw701"``, ``"act"``...: a template of
    the registry with a ``simulator``); ``options`` go to its constructor
    (``clock=``, ``state=``, ``mode=`` for the ASCII-capable ones)."""
    try:
        cls = find_template(device).hook("simulator")
    except TemplateError as e:
        raise ValueError(f"unknown device {device!r}: {e}") from None
    if cls is None:
        raise ValueError(
            f"device {device!r} has no drive simulator (its template has no simulator)"
        )
    sim: DriveSimulator = cls(**options)
    return sim


def describe_register(device: str, address: int, value: int) -> str | None:
    """A register value in the manual's terms (``"P680 status: running, forward,
    remote"``), or None when the register has no special meaning (or the
    template no ``describe``)."""
    try:
        describe = find_template(device).hook("describe")
    except TemplateError as e:
        raise ValueError(f"unknown device {device!r}: {e}") from None
    if describe is None:
        return None
    note: str | None = describe(address, value)
    return note


__all__ = [
    "ACT",
    "ACU",
    "ASCII_DEVICES",
    "CFW100",
    "CFW320",
    "CFW701",
    "CV100",
    "EXAMPLE_ADDRESS",
    "PROFILES",
    "SIMULATORS",
    "ACTSimulator",
    "ACUSimulator",
    "CFW100Simulator",
    "CFW320Simulator",
    "CFW701Simulator",
    "CV100Simulator",
    "CV100Status",
    "DriveSimulator",
    "DriveState",
    "ErrorAction",
    "InterfaceStatus",
    "ManualClock",
    "Motor",
    "Supervision",
    "Vectron",
    "VectronSimulator",
    "VectronStatus",
    "WegControl",
    "WegDrive",
    "WegSimulator",
    "WegStatus",
    "bonfiglioli",
    "cv100",
    "describe_register",
    "simulator",
    "weg",
]
