"""DataStore semantics: exception 2/3/4, atomic requests, ranges, callbacks, files."""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable

import pytest

from pyrtu.pdu.errors import SlaveException
from pyrtu.protocol.datastore import DataStore


def code(call: object) -> int:
    with pytest.raises(SlaveException) as info:
        call()  # type: ignore[operator]
    return info.value.code


def test_tables_and_sparse_ranges() -> None:
    store = DataStore()
    hr = store.holding_registers
    hr.add_range(0, [1, 2, 3])
    hr.add_range(100, [7] * 5)
    assert hr.ranges() == [(0, 3), (100, 5)]
    assert hr.read(0, 3) == [1, 2, 3]
    assert hr.read(102, 3) == [7, 7, 7]
    assert code(lambda: hr.read(2, 2)) == 2  # runs into the gap
    assert code(lambda: hr.read(99, 1)) == 2
    assert code(lambda: hr.read(104, 2)) == 2
    assert 101 in hr and 105 not in hr
    assert store.table("coils") is store.coils
    with pytest.raises(ValueError, match="no table"):
        store.table("registers")


def test_adjacent_ranges_serve_one_request() -> None:
    store = DataStore()
    hr = store.holding_registers
    hr.add_range(0, [0] * 5)
    hr.add_range(5, [0] * 5, validator=lambda a, v: v < 100)
    hr.write(3, [1, 2, 3, 4])
    assert hr.read(0, 10) == [0, 0, 0, 1, 2, 3, 4, 0, 0, 0]
    # the second range's validator rejects: nothing changes in either range
    assert code(lambda: hr.write(3, [9, 9, 500])) == 3
    assert hr.read(0, 10) == [0, 0, 0, 1, 2, 3, 4, 0, 0, 0]


def test_overlap_and_bad_values_rejected() -> None:
    store = DataStore()
    store.holding_registers.add_range(10, [0] * 10)
    with pytest.raises(ValueError, match="overlaps"):
        store.holding_registers.add_range(19, [0])
    with pytest.raises(ValueError, match="overlaps"):
        store.holding_registers.add_range(5, [0] * 6)
    store.holding_registers.add_range(20, [0])  # adjacent is fine
    with pytest.raises(ValueError, match=r"0\.\.65535"):
        store.holding_registers.add_range(30, [70000])
    with pytest.raises(ValueError, match="bool"):
        store.coils.add_range(0, [2])
    with pytest.raises(ValueError, match="at least one"):
        store.coils.add_range(0, [])
    with pytest.raises(ValueError, match="runs past"):
        store.coils.add_range(65535, [True, False])


def test_read_only_and_validator_give_3() -> None:
    store = DataStore()
    hr = store.holding_registers
    hr.add_range(0, [5], read_only=True)
    hr.add_range(1, [0, 0], validator=lambda address, value: value % 2 == 0)
    assert code(lambda: hr.write(0, [1])) == 3
    assert code(lambda: hr.write(1, [2, 3])) == 3
    assert hr.read(0, 3) == [5, 0, 0]
    hr.write(1, [2, 4])
    assert hr.read(1, 2) == [2, 4]
    hr.set(0, 6)  # the owner bypasses read-only
    assert hr.get(0) == 6


def test_validator_that_raises() -> None:
    store = DataStore()

    def picky(address: int, value: object) -> bool:
        if value == 13:
            raise SlaveException(6)  # busy
        if value == 14:
            raise RuntimeError("broken validator")
        return True

    store.holding_registers.add_range(0, [0], validator=picky)
    assert code(lambda: store.holding_registers.write(0, [13])) == 6
    assert code(lambda: store.holding_registers.write(0, [14])) == 4
    assert store.holding_registers.get(0) == 0


def test_failing_on_write_rolls_back_with_4() -> None:
    store = DataStore()
    calls: list[tuple[int, list[object]]] = []

    def first(address: int, values: list[object]) -> None:
        calls.append((address, values))

    def second(address: int, values: list[object]) -> None:
        raise OSError("actuator failed")

    store.coils.add_range(0, [False] * 4, on_write=first)
    store.coils.add_range(4, [False] * 4, on_write=second)
    assert code(lambda: store.coils.write(2, [True, True, True, True])) == 4
    assert calls == [(2, [True, True])]
    assert store.coils.read(0, 8) == [False] * 8  # rolled back in both ranges


def test_on_write_sees_the_new_values() -> None:
    store = DataStore()
    seen: list[object] = []
    hr = store.holding_registers
    hr.add_range(0, [0, 0], on_write=lambda a, v: seen.append((a, v, hr.get(0))))
    hr.write(0, [42])
    assert seen == [(0, [42], 42)]


def test_on_read_refreshes_and_fails_with_4() -> None:
    store = DataStore()
    ir = store.input_registers
    ticks = iter(range(100))

    def refresh(address: int, count: int) -> None:
        ir.set(0, next(ticks))

    ir.add_range(0, [0, 99], on_read=refresh)
    assert ir.read(0, 2) == [0, 99]
    assert ir.read(0, 1) == [1]

    def broken(address: int, count: int) -> None:
        raise ZeroDivisionError

    ir.add_range(10, [0], on_read=broken)
    assert code(lambda: ir.read(10, 1)) == 4


def test_owner_access() -> None:
    store = DataStore()
    store.discrete_inputs.add_range(0, [0, 1, 0])
    assert store.discrete_inputs.get_many(0, 3) == [False, True, False]
    store.discrete_inputs.set_many(0, [True, True])
    assert store.discrete_inputs.read(0, 3) == [True, True, False]
    with pytest.raises(KeyError):
        store.discrete_inputs.get(3)
    with pytest.raises(KeyError):
        store.discrete_inputs.set(3, True)
    with pytest.raises(ValueError):
        store.discrete_inputs.set(0, 5)


def test_check_write_does_not_store() -> None:
    store = DataStore()
    store.holding_registers.add_range(0, [0, 0])
    store.holding_registers.check_write(0, [1, 2])
    assert store.holding_registers.read(0, 2) == [0, 0]
    assert code(lambda: store.holding_registers.check_write(1, [1, 2])) == 2


def test_files() -> None:
    store = DataStore()
    f = store.add_file(4, [1, 2, 3], start=7)
    assert store.file(4) is f
    assert f.read(7, 3) == [1, 2, 3]
    assert code(lambda: store.file(5)) == 2
    assert code(lambda: f.read(6, 1)) == 2
    with pytest.raises(ValueError, match=r"1\.\.65535"):
        store.add_file(0, [1])
    with pytest.raises(ValueError, match="9999"):
        store.add_file(4, [0] * 2, start=9999)


def test_lock_serialises_owner_and_requests() -> None:
    store = DataStore()
    hr = store.holding_registers
    hr.add_range(0, [0, 0])

    def writer() -> None:
        for i in range(2000):
            hr.write(0, [i, i])

    thread = threading.Thread(target=writer)
    thread.start()
    for _ in range(2000):
        a, b = hr.read(0, 2)
        assert a == b  # never half a write
    thread.join()


def test_bulk_owner_access_is_a_loop_of_set() -> None:
    store = DataStore()
    hr = store.holding_registers
    hr.add_range(0, [0] * 3)
    hr.add_range(3, [0] * 2, read_only=True)  # adjacent: one bulk write spans both
    hr.add_range(10, [0] * 2)
    hr.set_each({4: 5, 0: 1, 11: 7})
    hr.set_each([(1, 2), (2, 3), (3, 4)])
    hr.set_many(10, [8])
    assert hr.get_many(0, 5) == [1, 2, 3, 4, 5] and hr.get_many(10, 2) == [8, 7]
    # the values before a bad address or value stay stored, as with `set`
    with pytest.raises(KeyError, match="address 5"):
        hr.set_many(3, [40, 50, 60])
    assert hr.get_many(3, 2) == [40, 50]
    for bad in (True, -1, 0x10000, 1.0, "1"):
        with pytest.raises(ValueError, match=r"holding_registers\[1\]"):
            hr.set_each({0: 9, 1: bad, 2: 9})
        assert hr.get_many(0, 3) == [9, 2, 3]
        hr.set(0, 1)
    with pytest.raises(KeyError, match="address 5"):
        hr.get_many(3, 3)
    assert hr.get_many(0, 0) == []
    coils = store.coils
    coils.add_range(0, [False] * 3)
    coils.set_each({0: 1, 2: True})
    coils.set_many(1, [0])
    assert coils.get_many(0, 3) == [True, False, True]
    assert all(type(v) is bool for v in coils.get_many(0, 3))
    with pytest.raises(ValueError, match="a bit"):
        coils.set_each({0: 2})


def test_version_changes_with_every_value_change() -> None:
    store = DataStore()
    hr = store.holding_registers
    seen = []

    def on_write(address: int, values: list[int | bool]) -> None:
        seen.append(hr.version)
        if values[0] == 13:
            raise SlaveException(4, "no")

    hr.add_range(0, [0] * 4, on_write=on_write, on_read=lambda a, n: None)
    versions = [hr.version]

    def changed() -> bool:
        versions.append(hr.version)
        return versions[-1] != versions[-2]

    hr.read(0, 4)
    hr.get(0)
    hr.get_many(0, 4)
    hr.check_read(0, 4)
    hr.check_write(0, [1])
    assert not changed()  # looks change nothing
    changes: list[Callable[[], None]] = [
        lambda: hr.set(0, 1),
        lambda: hr.set_each({1: 2}),
        lambda: hr.set_many(2, [3]),
        lambda: hr.write(3, [4]),
    ]
    for change in changes:
        change()
        assert changed()
    assert code(lambda: hr.write(0, [13])) == 4  # rolled back: a change too
    assert changed() and versions[-1] != seen[-1] and hr.get(0) == 1
    assert code(lambda: hr.write(9, [1])) == 2 and not changed()
    store.input_registers.add_range(0, [0])
    store.input_registers.set(0, 5)
    assert not changed()  # another table's


def _float32_words(value: float) -> list[int]:
    """The two registers of a float32, high word first (ABCD), from `struct`."""
    raw = struct.pack(">f", value)
    return [int.from_bytes(raw[:2], "big"), int.from_bytes(raw[2:], "big")]


# two float32s that differ in both registers: a torn read is neither of them
_A, _B = 1.0000001192092896, -2.250000476837158
_WORDS = (_float32_words(_A), _float32_words(_B))


def test_set_many_and_set_each_are_never_read_torn() -> None:
    """The owner's multi-register updates (#27.15: the docs' way to store a float32)
    are one update each: a request's read (`read`, what a slave serves) and
    `get_many` running meanwhile see the old value or the new one, never one register
    of each."""
    assert all(a != b for a, b in zip(*_WORDS, strict=True))
    store = DataStore()
    hr = store.holding_registers
    hr.add_range(0, _WORDS[0])
    stop = threading.Event()

    def owner() -> None:
        i = 0
        while not stop.is_set():
            words = _WORDS[i % 2]
            if i % 4 < 2:
                hr.set_many(0, words)
            else:
                hr.set_each({0: words[0], 1: words[1]})
            i += 1

    thread = threading.Thread(target=owner)
    thread.start()
    try:
        seen = set()
        n = 0
        give_up = time.monotonic() + 30  # a safety net: a loaded machine may hold the owner
        while n < 20000 or (len(seen) < 2 and time.monotonic() < give_up):
            pair = hr.read(0, 2) if n % 2 else hr.get_many(0, 2)
            assert pair in _WORDS, f"torn: {pair}"
            seen.add(tuple(pair))
            n += 1
    finally:
        stop.set()
        thread.join()
    assert len(seen) == 2  # the reader did see both values: the updates ran meanwhile


def test_a_master_never_reads_a_set_many_float32_torn() -> None:
    """The same through a real slave on a pseudo-terminal, read by a master as the
    README shows (`pyrtu.decode_float32`): every value read is one the owner stored."""
    from pyrtu import Master, Slave, decode_float32

    vbus = pytest.importorskip("pyrtu.vbus")
    store = DataStore()
    store.holding_registers.add_range(0, _WORDS[0])
    stop = threading.Event()

    def owner() -> None:
        i = 0
        while not stop.is_set():
            store.holding_registers.set_many(0, _WORDS[i % 2])
            i += 1

    with vbus.VirtualBus(2, baudrate=115200, parity="N") as bus:
        slave = Slave(bus.paths[1], address=1, store=store, baudrate=115200, parity="N")
        slave.start()
        thread = threading.Thread(target=owner)
        thread.start()
        try:
            with Master(bus.paths[0], baudrate=115200, parity="N", timeout=0.5) as m:
                values = {decode_float32(m.read_holding_registers(1, 0, 2)) for _ in range(300)}
        finally:
            stop.set()
            thread.join()
            slave.close()
    assert values <= {_A, _B}, values
