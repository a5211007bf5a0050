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

`SIMULATORS`/`PROFILES` map the command line's device names (cfw100, cfw320,
cfw701, cv100, act, acu) to the classes; `describe_register` names a register value
in the manual's terms (for monitors).
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

SIMULATORS: Mapping[str, type[DriveSimulator]] = {
    "cfw100": CFW100Simulator,
    "cfw320": CFW320Simulator,
    "cfw701": CFW701Simulator,
    "cv100": CV100Simulator,
    "act": ACTSimulator,
    "acu": ACUSimulator,
}
PROFILES: Mapping[str, type[Any]] = {
    "cfw100": CFW100,
    "cfw320": CFW320,
    "cfw701": CFW701,
    "cv100": CV100,
    "act": ACT,
    "acu": ACU,
}
#: the address the manual's examples use (a simulator's natural default)
EXAMPLE_ADDRESS: Mapping[str, int] = {
    "cfw100": 1,
    "cfw320": 1,
    "cfw701": 1,
    "cv100": 5,
    "act": 1,
    "acu": 1,
}
#: which devices speak ASCII as well as RTU
ASCII_DEVICES = frozenset({"cv100", "act", "acu"})


def simulator(device: str, **options: Any) -> DriveSimulator:
    """A simulator by command-line name (``"cfw701"``, ``"act"``...); ``options`` go to
    its constructor (``clock=``, ``state=``, ``mode=`` for the ASCII-capable ones)."""
    try:
        cls = SIMULATORS[device.lower()]
    except KeyError:
        raise ValueError(f"unknown device {device!r}; devices: {', '.join(SIMULATORS)}") from None
    return cls(**options)


def describe_register(device: str, address: int, value: int) -> str | None:
    """A register value in the manual's terms (``"P680 status: running, forward,
    remote"``), or None when the register has no special meaning."""
    d = device.lower()
    if d in ("cfw100", "cfw320", "cfw701"):
        return weg.describe_register(d.upper(), address, value)
    if d == "cv100":
        return cv100.describe_register(address, value)
    if d in ("act", "acu"):
        return bonfiglioli.describe_register(address, value)
    raise ValueError(f"unknown device {device!r}; devices: {', '.join(SIMULATORS)}")


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
