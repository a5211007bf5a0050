"""The image of a DataStore (csrc/rtu_image.c and its twin pyrtu/core/_pure/image.py):
plain reads answered byte for byte as pyrtu's own slave answers them, everything else
deferred.

MODBUS Application Protocol V1.1b3 6.1-6.4: FC 01/02 quantity 1..2000, byte count
ceil(q / 8), bits LSB first, unused high bits 0; FC 03/04 quantity 1..125, byte count
2q, registers big-endian.  Both backends run every case (the C one skips only where the
core is not built, and fails then with PYRTU_REQUIRE_C=1).
"""

from __future__ import annotations

import random
import struct
from collections.abc import Callable, Sequence
from typing import Any

import pytest
from c_core import missing
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import pyrtu
from pyrtu.core._pure.image import HELD, PLAIN, image_answer, image_check
from pyrtu.protocol.datastore import DataStore
from pyrtu.tcp.server import TcpServer

Range = tuple[int, int, Sequence[int]]
Tables = list[list[Range]]
Answer = Callable[[Tables, bytes], "bytes | None"]
Check = Callable[[Tables], bool]


def _core() -> tuple[Any, Any]:
    if "c" not in pyrtu.available_backends():
        missing()
    from pyrtu.core._rtu_core import ffi, lib

    return ffi, lib


class CImage:
    """An rtu_image over cffi memory holding ``tables`` (kept alive with it)."""

    def __init__(self, tables: Tables) -> None:
        ffi, lib = _core()
        self.ffi, self.lib = ffi, lib
        self.img = ffi.new("rtu_image *")
        self.keep: list[Any] = []
        for t, ranges in enumerate(tables):
            if not ranges:
                continue
            arr = ffi.new("rtu_image_range[]", len(ranges))
            for i, (start, flags, values) in enumerate(ranges):
                vals = ffi.new("uint16_t[]", [v & 0xFFFF for v in values])
                self.keep.append(vals)
                arr[i].start = start
                arr[i].count = len(values)
                arr[i].flags = flags
                arr[i].values = vals
            self.keep.append(arr)
            self.img.ranges[t] = arr
            self.img.nranges[t] = len(ranges)

    def answer(self, pdu: bytes) -> bytes | None:
        out = self.ffi.new("uint8_t[]", 253)
        n = self.ffi.new("size_t *")
        rc = self.lib.rtu_image_answer(self.img, pdu, len(pdu), out, 253, n)
        if rc == self.lib.RTU_IMAGE_DEFER:
            return None
        assert rc == self.lib.RTU_OK, rc
        return bytes(self.ffi.buffer(out, n[0]))

    def check(self) -> bool:
        rc = self.lib.rtu_image_check(self.img)
        assert rc in (self.lib.RTU_OK, self.lib.RTU_EINVAL)
        return bool(rc == self.lib.RTU_OK)


def _c_answer(tables: Tables, pdu: bytes) -> bytes | None:
    return CImage(tables).answer(pdu)


def _c_check(tables: Tables) -> bool:
    return CImage(tables).check()


@pytest.fixture(params=["c", "python"])
def impl(request: pytest.FixtureRequest) -> tuple[Answer, Check]:
    if request.param == "c":
        _core()
        return _c_answer, _c_check
    return image_answer, image_check


def _pdu(fc: int, address: int, quantity: int) -> bytes:
    return struct.pack(">BHH", fc, address & 0xFFFF, quantity & 0xFFFF)


def _tables(
    coils: list[Range] | None = None,
    di: list[Range] | None = None,
    hr: list[Range] | None = None,
    ir: list[Range] | None = None,
) -> Tables:
    return [coils or [], di or [], hr or [], ir or []]


def _regs(fc: int, values: Sequence[int]) -> bytes:
    return bytes((fc, 2 * len(values))) + struct.pack(f">{len(values)}H", *values)


# ------------------------------------------------------------------ boundaries

WHOLE_BITS = [(0, PLAIN, [i % 3 == 0 for i in range(65536)])]
WHOLE_REGS = [(0, PLAIN, [(i * 7919) & 0xFFFF for i in range(65536)])]


def test_quantity_limits_of_bits(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    for fc, tables in ((1, _tables(coils=WHOLE_BITS)), (2, _tables(di=WHOLE_BITS))):
        full = answer(tables, _pdu(fc, 0, 2000))
        assert full is not None and full[:2] == bytes((fc, 250)) and len(full) == 252
        assert answer(tables, _pdu(fc, 0, 2001)) is None
        assert answer(tables, _pdu(fc, 0, 0)) is None
        one = answer(tables, _pdu(fc, 0, 1))
        assert one == bytes((fc, 1, 1))  # address 0: 0 % 3 == 0 -> on


def test_quantity_limits_of_registers(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    values = WHOLE_REGS[0][2]
    for fc, tables in ((3, _tables(hr=WHOLE_REGS)), (4, _tables(ir=WHOLE_REGS))):
        assert answer(tables, _pdu(fc, 10, 125)) == _regs(fc, values[10:135])
        assert answer(tables, _pdu(fc, 10, 126)) is None
        assert answer(tables, _pdu(fc, 10, 0)) is None


def test_address_plus_quantity_at_65536(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    values = WHOLE_REGS[0][2]
    tables = _tables(coils=WHOLE_BITS, hr=WHOLE_REGS)
    assert answer(tables, _pdu(3, 65536 - 125, 125)) == _regs(3, values[-125:])
    assert answer(tables, _pdu(3, 65536 - 124, 125)) is None  # 65537
    assert answer(tables, _pdu(3, 65535, 1)) == _regs(3, [values[65535]])
    assert answer(tables, _pdu(3, 65535, 2)) is None
    last = answer(tables, _pdu(1, 65536 - 2000, 2000))
    assert last is not None and len(last) == 252
    assert answer(tables, _pdu(1, 65536 - 1999, 2000)) is None


def test_the_last_address_of_a_range(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    tables = _tables(hr=[(100, PLAIN, [1, 2, 3, 4])])
    assert answer(tables, _pdu(3, 103, 1)) == _regs(3, [4])
    assert answer(tables, _pdu(3, 100, 4)) == _regs(3, [1, 2, 3, 4])
    assert answer(tables, _pdu(3, 100, 5)) is None  # 104 is outside
    assert answer(tables, _pdu(3, 104, 1)) is None
    assert answer(tables, _pdu(3, 99, 2)) is None  # 99 is outside
    assert answer(tables, _pdu(3, 0, 1)) is None  # before the first range


def test_a_read_spans_adjacent_plain_ranges_not_a_gap(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    adjacent = _tables(ir=[(0, PLAIN, [10, 11]), (2, PLAIN, [12]), (3, PLAIN, [13, 14])])
    assert answer(adjacent, _pdu(4, 1, 4)) == _regs(4, [11, 12, 13, 14])
    gap = _tables(ir=[(0, PLAIN, [10, 11]), (3, PLAIN, [13, 14])])
    assert answer(gap, _pdu(4, 0, 2)) == _regs(4, [10, 11])
    assert answer(gap, _pdu(4, 1, 3)) is None  # 2 lies in the gap
    assert answer(gap, _pdu(4, 2, 1)) is None
    assert answer(gap, _pdu(4, 3, 2)) == _regs(4, [13, 14])


def test_a_held_range_is_deferred(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    tables = _tables(hr=[(0, PLAIN, [1, 2]), (2, HELD, [3]), (3, PLAIN, [4])])
    assert answer(tables, _pdu(3, 0, 2)) == _regs(3, [1, 2])
    assert answer(tables, _pdu(3, 3, 1)) == _regs(3, [4])
    assert answer(tables, _pdu(3, 2, 1)) is None
    assert answer(tables, _pdu(3, 1, 2)) is None
    assert answer(tables, _pdu(3, 0, 4)) is None


def test_pdu_length_and_function(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    tables = _tables(coils=WHOLE_BITS, di=WHOLE_BITS, hr=WHOLE_REGS, ir=WHOLE_REGS)
    pdu = _pdu(3, 0, 1)
    assert answer(tables, pdu) is not None
    assert answer(tables, pdu[:4]) is None
    assert answer(tables, pdu + b"\x00") is None
    assert answer(tables, b"") is None
    for fc in (0, 5, 6, 0x83, 0x81, 0xFF, 16, 23):
        assert answer(tables, bytes((fc,)) + pdu[1:]) is None, fc


def test_each_function_reads_its_own_table(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    tables = _tables(
        coils=[(0, PLAIN, [1])], di=[(1, PLAIN, [1])], hr=[(2, PLAIN, [2])], ir=[(3, PLAIN, [3])]
    )
    assert answer(tables, _pdu(1, 0, 1)) == b"\x01\x01\x01"
    assert answer(tables, _pdu(1, 1, 1)) is None
    assert answer(tables, _pdu(2, 1, 1)) == b"\x02\x01\x01"
    assert answer(tables, _pdu(2, 0, 1)) is None
    assert answer(tables, _pdu(3, 2, 1)) == _regs(3, [2])
    assert answer(tables, _pdu(3, 3, 1)) is None
    assert answer(tables, _pdu(4, 3, 1)) == _regs(4, [3])
    assert answer(tables, _pdu(4, 2, 1)) is None


def test_bit_packing(impl: tuple[Answer, Check]) -> None:
    """[AP] 6.1's example: coils 20..38 = CD 6B 05 (LSB first, high bits of the last
    byte 0), and any nonzero value reads as 1."""
    answer, _ = impl
    bits = [1, 0, 1, 1, 0, 0, 1, 1, 1, 1, 0, 1, 0, 1, 1, 0, 1, 0, 1]  # 0xCD, 0x6B, 0x05
    assert answer(_tables(coils=[(20, PLAIN, bits)]), _pdu(1, 20, 19)) == bytes.fromhex(
        "0103cd6b05"
    )
    nonzero = [v * 0x8001 for v in bits]  # 0x8001: bit 0 and bit 15
    assert answer(_tables(di=[(19, PLAIN, [0, *nonzero])]), _pdu(2, 20, 19)) == bytes.fromhex(
        "0203cd6b05"
    )
    eight = answer(_tables(coils=[(0, PLAIN, [1] * 16)]), _pdu(1, 0, 8))
    assert eight == b"\x01\x01\xff"
    nine = answer(_tables(coils=[(0, PLAIN, [1] * 16)]), _pdu(1, 0, 9))
    assert nine == b"\x01\x02\xff\x01"


def test_registers_are_big_endian(impl: tuple[Answer, Check]) -> None:
    answer, _ = impl
    tables = _tables(hr=[(0x6B, PLAIN, [0x022B, 0x0000, 0x0064])])
    # [AP] 6.3's example: registers 108-110 = 02 2B, 00 00, 00 64
    assert answer(tables, _pdu(3, 0x6B, 3)) == bytes.fromhex("0306022b00000064")


def test_check(impl: tuple[Answer, Check]) -> None:
    _, check = impl
    good = _tables(hr=[(0, PLAIN, [1]), (1, HELD, [2]), (65535, PLAIN, [3])])
    assert check(good)
    assert check(_tables())
    assert check(_tables(coils=[(0, PLAIN, [0] * 65536)]))
    assert not check(_tables(hr=[(1, PLAIN, [1]), (0, PLAIN, [1])]))  # unsorted
    assert not check(_tables(hr=[(0, PLAIN, [1, 2]), (1, PLAIN, [1])]))  # overlapping
    assert not check(_tables(hr=[(5, PLAIN, [1]), (5, PLAIN, [1])]))  # the same start
    assert not check(_tables(hr=[(0, PLAIN, [])]))  # count 0
    assert not check(_tables(hr=[(65535, PLAIN, [1, 2])]))  # past 65535
    assert not check(_tables(hr=[(65536, PLAIN, [1])]))
    assert not check(_tables(ir=[(0, 2, [1])]))  # unknown flags


def test_c_check_refuses_null_pointers() -> None:
    ffi, lib = _core()
    assert lib.rtu_image_check(ffi.NULL) == lib.RTU_EINVAL
    img = ffi.new("rtu_image *")
    assert lib.rtu_image_check(img) == lib.RTU_OK
    img.nranges[1] = 1  # ranges[1] is NULL
    assert lib.rtu_image_check(img) == lib.RTU_EINVAL
    r = ffi.new("rtu_image_range[1]")
    r[0].start, r[0].count, r[0].flags = 0, 1, lib.RTU_IMAGE_PLAIN
    img.ranges[1] = r
    assert lib.rtu_image_check(img) == lib.RTU_EINVAL  # values NULL
    vals = ffi.new("uint16_t[1]")
    r[0].values = vals
    assert lib.rtu_image_check(img) == lib.RTU_OK


def test_c_answer_refuses_null_and_small_out() -> None:
    ffi, lib = _core()
    image = CImage(_tables(hr=[(0, PLAIN, [1])]))
    out = ffi.new("uint8_t[]", 253)
    n = ffi.new("size_t *")
    pdu = _pdu(3, 0, 1)
    answer = lib.rtu_image_answer
    assert answer(image.img, pdu, 5, out, 253, n) == lib.RTU_OK
    assert answer(image.img, pdu, 5, out, 252, n) == lib.RTU_EINVAL
    assert answer(ffi.NULL, pdu, 5, out, 253, n) == lib.RTU_EINVAL
    assert answer(image.img, ffi.NULL, 5, out, 253, n) == lib.RTU_EINVAL
    assert answer(image.img, pdu, 5, ffi.NULL, 253, n) == lib.RTU_EINVAL
    assert answer(image.img, pdu, 5, out, 253, ffi.NULL) == lib.RTU_EINVAL
    # an empty table (no array at all) defers
    assert answer(image.img, _pdu(4, 0, 1), 5, out, 253, n) == lib.RTU_IMAGE_DEFER


# ------------------------------------------------------------ the slave's answer


def _random_tables(rng: random.Random, with_held: bool = True) -> Tables:
    tables: Tables = []
    for t in range(4):
        ranges: list[Range] = []
        pos = rng.choice([0, 0, 1, 50, 65000])
        for _ in range(rng.randint(0, 5)):
            pos += rng.choice([0, 0, 1, 3, 200])
            count = rng.choice([1, 2, 7, 8, 9, 100, 130, 2100])
            if pos >= 65536:
                break
            count = min(count, 65536 - pos)
            flags = HELD if with_held and rng.random() < 0.2 else PLAIN
            if t < 2:
                values = [rng.randint(0, 1) for _ in range(count)]
            else:
                values = [rng.randint(0, 0xFFFF) for _ in range(count)]
            ranges.append((pos, flags, values))
            pos += count
        tables.append(ranges)
    return tables


def _store(tables: Tables, reads: list[tuple[int, int]]) -> DataStore:
    store = DataStore()
    names = (store.coils, store.discrete_inputs, store.holding_registers, store.input_registers)
    for table, ranges in zip(names, tables, strict=True):
        for start, flags, values in ranges:
            vals = [bool(v) for v in values] if table.bits else list(values)
            on_read = (lambda a, n: reads.append((a, n))) if flags == HELD else None
            table.add_range(start, vals, on_read=on_read)
    return store


def _requests(rng: random.Random, tables: Tables) -> list[bytes]:
    out = []
    for _ in range(60):
        fc = rng.choice([1, 2, 3, 4, 1, 3, 0, 5, 6, 0x83])
        ranges = tables[(fc - 1) % 4] if 1 <= fc <= 4 else []
        if ranges and rng.random() < 0.8:
            start, _, values = rng.choice(ranges)
            address = start + rng.randint(-2, len(values))
        else:
            address = rng.randint(0, 65535)
        limit = 2000 if fc in (1, 2) else 125
        quantity = rng.choice([0, 1, 2, 8, 9, limit, limit + 1, rng.randint(1, limit)])
        pdu = _pdu(fc, address, quantity)
        cut = rng.random()
        if cut < 0.05:
            pdu = pdu[:4]
        elif cut < 0.1:
            pdu += b"\x00"
        out.append(pdu)
    return out


def test_the_image_answers_as_the_slave_does(impl: tuple[Answer, Check]) -> None:
    """On random images and requests: whatever the image answers, pyrtu's slave
    (`TcpServer.for_store(1, store).app.execute`) answers alike; what it defers is a
    request the slave answers with an exception, or from a held range (its on_read
    runs), or one that is not a plain read."""
    answer, check = impl
    rng = random.Random(2024)
    answered = deferred = 0
    for _ in range(40):
        tables = _random_tables(rng)
        assert check(tables)
        reads: list[tuple[int, int]] = []
        app = TcpServer.for_store(1, _store(tables, reads)).app
        for pdu in _requests(rng, tables):
            mine = answer(tables, pdu)
            reads.clear()
            theirs = app.execute(1, pdu)
            assert theirs is not None
            if mine is not None:
                assert mine == theirs, pdu.hex()
                assert not reads  # (no held range was read)
                answered += 1
            else:
                plain_read = len(pdu) == 5 and 1 <= pdu[0] <= 4
                assert not plain_read or theirs[0] & 0x80 or reads, (pdu.hex(), theirs.hex())
                deferred += 1
    assert answered > 200 and deferred > 200, (answered, deferred)


SETTINGS = settings(
    max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@SETTINGS
@given(seed=st.integers(0, 2**32 - 1), pdu=st.binary(min_size=0, max_size=7))
def test_c_and_twin_agree(seed: int, pdu: bytes) -> None:
    """The C image and the twin on the same random images, any PDU bytes and the
    requests the slave test draws."""
    _core()
    rng = random.Random(seed)
    tables = _random_tables(rng)
    image = CImage(tables)
    assert image.check() and image_check(tables)
    for p in [pdu, *_requests(rng, tables)[:20]]:
        assert image.answer(p) == image_answer(tables, p), p.hex()


def test_the_twin_check_refuses_what_c_cannot_hold() -> None:
    assert not image_check([[], [], []])  # three tables
    assert not image_check(_tables(hr=[(0, PLAIN, [0x10000])]))
    assert not image_check(_tables(hr=[(0, PLAIN, [-1])]))
