"""The deterministic register pattern every interop peer serves.

The same formulas are in ``libmodbus_server.c`` (``pattern_*``), in
``pymodbus_server.py`` and in the pyrtu slaves the tests build, so a test can
check every value it reads.  The slave address is part of each formula: an
answer from the wrong slave on a shared bus is a wrong value, not a lucky match.

===================  =========  ==========================================
table                addresses  value at address ``i`` of slave ``s``
===================  =========  ==========================================
coils                0..1999    ``(i + s) % 3 == 0``
discrete inputs      0..1999    ``(i * 5 + s) % 7 < 3``
holding registers    0..999     ``(i * 3 + 1 + s * 1000) % 65536``
input registers      0..999     ``(i * 7 + 2 + s * 2000) % 65536``
===================  =========  ==========================================

Addresses outside those ranges answer exception 2 (illegal data address).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pyrtu.protocol.datastore import DataStore

N_BITS = 2000
N_REGS = 1000


def coil(slave: int, i: int) -> bool:
    return (i + slave) % 3 == 0


def discrete(slave: int, i: int) -> bool:
    return (i * 5 + slave) % 7 < 3


def holding(slave: int, i: int) -> int:
    return (i * 3 + 1 + slave * 1000) % 65536


def input_reg(slave: int, i: int) -> int:
    return (i * 7 + 2 + slave * 2000) % 65536


def coils(slave: int, address: int, count: int) -> list[bool]:
    return [coil(slave, i) for i in range(address, address + count)]


def discretes(slave: int, address: int, count: int) -> list[bool]:
    return [discrete(slave, i) for i in range(address, address + count)]


def holdings(slave: int, address: int, count: int) -> list[int]:
    return [holding(slave, i) for i in range(address, address + count)]


def inputs(slave: int, address: int, count: int) -> list[int]:
    return [input_reg(slave, i) for i in range(address, address + count)]


def pattern_store(slave: int) -> DataStore:
    """A pyrtu DataStore holding the four tables of slave `slave`."""
    from pyrtu.protocol.datastore import DataStore  # here: pymodbus_server.py runs without pyrtu

    store = DataStore()
    store.coils.add_range(0, coils(slave, 0, N_BITS))
    store.discrete_inputs.add_range(0, discretes(slave, 0, N_BITS))
    store.holding_registers.add_range(0, holdings(slave, 0, N_REGS))
    store.input_registers.add_range(0, inputs(slave, 0, N_REGS))
    return store
