"""The register types of `pyrtu.pdu.codecs` against an independent encoder: `struct`
packs the value big-endian (bytes A B C ...), and the order's own letters say which
bytes each register carries (``CDAB``: register 0 is bytes C, D).  Every type, every
order, the boundaries of every integer type, NaN, the infinities and float16's
subnormals."""

from __future__ import annotations

import math
import struct

import pytest

from pyrtu import data
from pyrtu.pdu import codecs

#: struct format of each fixed-size number type
FORMATS = {
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float16": "e",
    "float32": "f",
    "float64": "d",
}
ORDERS = {1: ("AB", "BA"), 2: codecs.ORDERS_32, 4: codecs.ORDERS_64}


def by_letters(big_endian: bytes, order: str) -> list[int]:
    """Registers carrying ``big_endian``'s bytes as ``order``'s letters say."""
    at = [ord(c) - ord("A") for c in order]
    return [big_endian[at[k]] << 8 | big_endian[at[k + 1]] for k in range(0, len(at), 2)]


def integer_samples(fmt: str) -> list[int]:
    bits = struct.calcsize(fmt) * 8
    if fmt.islower():
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    else:
        lo, hi = 0, (1 << bits) - 1
    return [lo, lo + 1, -1 if lo else 1, 0, 1, 0x1234 % (hi + 1), hi - 1, hi]


def float_samples(fmt: str) -> list[float]:
    tiny = {"e": 2.0**-24, "f": 2.0**-149, "d": 5e-324}[fmt]  # the smallest subnormal
    big = {"e": 65504.0, "f": 3.4028234663852886e38, "d": 1.7976931348623157e308}[fmt]
    return [0.0, -0.0, 1.5, -2.25, 0.1, tiny, -tiny, 3 * tiny, big, -big, math.inf, -math.inf]


CASES = [
    (name, order, value)
    for name, fmt in FORMATS.items()
    for order in ORDERS[struct.calcsize(fmt) // 2]
    for value in (integer_samples(fmt) if fmt in "hHiIqQ" else float_samples(fmt))
]


@pytest.mark.parametrize(("name", "order", "value"), CASES)
def test_round_trip_against_struct(name: str, order: str, value: float) -> None:
    fmt = FORMATS[name]
    packed = struct.pack(">" + fmt, value)
    want = by_letters(packed, order)
    assert codecs.encode(name, value, order) == want
    got = codecs.decode(name, want, order)
    expected = struct.unpack(">" + fmt, packed)[0]  # a float as the type holds it
    assert got == expected and type(got) is type(expected)
    if isinstance(expected, float):
        assert math.copysign(1, got) == math.copysign(1, expected)  # type: ignore[arg-type]
    # at an offset inside a block, as the poller reads it
    block = [0xDEAD, *want, 0xBEEF]
    assert codecs.decoder(name, order)(block, 1) == expected


@pytest.mark.parametrize("name", ["float16", "float32", "float64"])
@pytest.mark.parametrize("order", ["ABCD", "DCBA"])
def test_nan_both_ways(name: str, order: str) -> None:
    regs = codecs.encode(name, math.nan, order)
    fmt = FORMATS[name]
    assert regs == by_letters(struct.pack(">" + fmt, math.nan), codecs.normalize_order(name, order))
    got = codecs.decode(name, regs, order)
    assert isinstance(got, float) and math.isnan(got)


def test_float16_subnormals_are_exact() -> None:
    # 0x0001 is the smallest subnormal half (2**-24); 0x03FF the largest (1023 * 2**-24)
    assert codecs.decode("float16", [0x0001]) == 2.0**-24
    assert codecs.decode("float16", [0x03FF]) == 1023 * 2.0**-24
    assert codecs.decode("float16", [0x8001]) == -(2.0**-24)
    assert codecs.encode("float16", 2.0**-24) == [0x0001]
    assert codecs.encode("float16", 2.0**-25 * 1.5) == [0x0001]  # rounds to nearest
    assert codecs.decode("float16", [0x7C00]) == math.inf


@pytest.mark.parametrize(
    ("name", "value"),
    [("float16", 65520.0), ("float16", -1e6), ("float32", 3.5e38), ("float64", 10**400)],
)
def test_float_overflow_is_refused(name: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"out of the {name} range"):
        codecs.encode(name, value)


@pytest.mark.parametrize(
    ("name", "low", "high"),
    [("int8", -128, 127), ("uint8", 0, 255), ("int16", -32768, 32767), ("uint16", 0, 65535),
     ("int32", -(2**31), 2**31 - 1), ("uint32", 0, 2**32 - 1), ("int64", -(2**63), 2**63 - 1),
     ("uint64", 0, 2**64 - 1), ("bcd16", 0, 9999), ("bcd32", 0, 99_999_999)],
)  # fmt: skip
def test_integer_ranges_exactly_at_the_boundary(name: str, low: int, high: int) -> None:
    for v in (low, high):
        assert codecs.decode(name, codecs.encode(name, v)) == v
    for v in (low - 1, high + 1):
        with pytest.raises(ValueError, match=rf"{low}\.\.{high}"):
            codecs.encode(name, v)
    with pytest.raises(ValueError, match="integer"):
        codecs.encode(name, 1.5)


def test_bytes_of_a_register() -> None:
    # hand-built: 0x80FF holds -128 / 128 in its high byte and -1 / 255 in its low one
    assert codecs.decode("int8", [0x80FF], "high") == -128
    assert codecs.decode("uint8", [0x80FF], "high") == 128
    assert codecs.decode("int8", [0x80FF], "low") == -1
    assert codecs.decode("uint8", [0x80FF], "low") == 255
    assert codecs.encode("int8", -1, "high") == [0xFF00]
    assert codecs.encode("uint8", 0x7F, "low") == [0x007F]
    assert codecs.normalize_order("uint8", "ABCD") == "high"  # a word order says nothing
    with pytest.raises(ValueError, match="high, low"):
        codecs.normalize_order("uint8", "middle")


def test_bcd_hand_built() -> None:
    assert codecs.decode("bcd16", [0x1234]) == 1234
    assert codecs.encode("bcd16", 905) == [0x0905]
    assert codecs.decode("bcd32", [0x1234, 0x5678]) == 12345678
    assert codecs.decode("bcd32", [0x5678, 0x1234], "CDAB") == 12345678
    assert codecs.decode("bcd32", [0x3412, 0x7856], "BADC") == 12345678
    assert codecs.decode("bcd32", [0x7856, 0x3412], "DCBA") == 12345678
    assert codecs.encode("bcd32", 12345678, "DCBA") == [0x7856, 0x3412]
    assert codecs.decode("bcd16", [0x12A4]) is None  # a nibble above 9: no number


def test_strings_hand_built() -> None:
    assert codecs.encode("string", "ABC", count=3) == [0x4142, 0x4300, 0]
    assert codecs.encode("string", "ABC", "BA", count=2) == [0x4241, 0x0043]
    assert codecs.decode("string", [0x4142, 0x4300, 0x5858]) == "ABC"  # cut at the NUL
    assert codecs.decode("string", [0x4142, 0x2020]) == "AB"  # trailing spaces trimmed
    assert codecs.decode("string", [0x4241, 0x2043], "BA") == "ABC"
    assert codecs.encode("string1", "AB", count=3) == [0x41, 0x42, 0]
    assert codecs.encode("string1", "AB", "BA", count=2) == [0x4100, 0x4200]
    assert codecs.decode("string1", [0xFF41, 0x0042, 0]) == "AB"  # the low byte
    assert codecs.decode("string", [0xE9FC]) == "éü"  # Latin-1: every byte is a character
    with pytest.raises(ValueError, match="at most 4"):
        codecs.encode("string", "ABCDE", count=2)
    with pytest.raises(ValueError, match="at most 2"):
        codecs.encode("string1", "ABC", count=2)


def test_orders_of_each_width() -> None:
    assert codecs.normalize_order("float64", "cdab") == "GHEFCDAB"
    assert codecs.normalize_order("int64", "DCBA") == "HGFEDCBA"
    assert codecs.normalize_order("int32", "BADCFEHG") == "BADC"
    assert codecs.normalize_order("uint16", "DCBA") == "BA"
    assert codecs.normalize_order("string", "CDAB") == "AB"
    assert codecs.normalize_order("float32", None) == "ABCD"
    with pytest.raises(ValueError, match="ABCDEFGH, GHEFCDAB, BADCFEHG, HGFEDCBA"):
        codecs.normalize_order("uint64", "ABDC")


def test_field_masks_follow_fc22() -> None:
    # Application Protocol 6.16's example: current 0x12, and 0xF2, or 0x25 -> 0x17
    assert codecs.apply_masks(0x0012, 0x00F2, 0x0025) == 0x0017
    and_mask, or_mask = codecs.field_masks(4, 3, 5)
    assert (and_mask, or_mask) == (0xFF8F, 0x0050)
    assert codecs.apply_masks(0xFFFF, and_mask, or_mask) == 0xFFDF
    assert codecs.apply_masks(0x0000, and_mask, or_mask) == 0x0050
    with pytest.raises(ValueError, match=r"0\.\.7"):
        codecs.field_masks(4, 3, 8)


def test_data_module_takes_every_number_type() -> None:
    regs = data.encode_values("int64", [-1, 2], "CDAB")
    assert regs == by_letters(struct.pack(">q", -1), "GHEFCDAB") + by_letters(
        struct.pack(">q", 2), "GHEFCDAB"
    )
    assert data.decode_values("int64", regs, "CDAB") == [-1, 2]
    assert data.decode("float64", data.encode("float64", 0.1)) == 0.1
    assert set(data.TYPES) >= {"int8", "uint64", "float16", "bcd32", "string1"}
