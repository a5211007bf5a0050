"""Data helpers: 32-bit values over two registers in the four orders, and strings."""

from __future__ import annotations

import math
import struct

import pytest

from pyrtu.pdu.data import (
    FLOAT32_MAX,
    ORDERS,
    decode_float32,
    decode_int32,
    decode_string,
    decode_uint32,
    decode_values,
    encode_float32,
    encode_int32,
    encode_string,
    encode_uint32,
    encode_values,
)

# 0x12345678: A=0x12 B=0x34 C=0x56 D=0x78
EXPECTED = {
    "ABCD": [0x1234, 0x5678],
    "CDAB": [0x5678, 0x1234],
    "BADC": [0x3412, 0x7856],
    "DCBA": [0x7856, 0x3412],
}


@pytest.mark.parametrize("order", ORDERS)
def test_uint32_layout(order: str) -> None:
    assert encode_uint32(0x12345678, order) == EXPECTED[order]
    assert decode_uint32(EXPECTED[order], order) == 0x12345678


@pytest.mark.parametrize("order", ORDERS)
def test_int32_negative(order: str) -> None:
    regs = encode_int32(-2, order)
    # -2 = FF FF FF FE
    assert (
        regs
        == {
            "ABCD": [0xFFFF, 0xFFFE],
            "CDAB": [0xFFFE, 0xFFFF],
            "BADC": [0xFFFF, 0xFEFF],
            "DCBA": [0xFEFF, 0xFFFF],
        }[order]
    )
    assert decode_int32(regs, order) == -2
    assert decode_uint32(regs, order) == 0xFFFFFFFE


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("value", [0.0, 1.5, -273.15, 3.4e38, 1e-40, math.inf, -math.inf])
def test_float32_round_trip(order: str, value: float) -> None:
    regs = encode_float32(value, order)
    assert all(0 <= r <= 0xFFFF for r in regs)
    assert decode_float32(regs, order) == struct.unpack(">f", struct.pack(">f", value))[0]


def test_float32_known_bytes() -> None:
    # 100.25 = 0x42C88000
    assert encode_float32(100.25) == [0x42C8, 0x8000]
    assert encode_float32(100.25, "CDAB") == [0x8000, 0x42C8]
    assert encode_float32(100.25, "BADC") == [0xC842, 0x0080]
    assert encode_float32(100.25, "DCBA") == [0x0080, 0xC842]
    assert decode_float32([0x42C8, 0x8000]) == 100.25
    assert math.isnan(decode_float32([0x7FC0, 0x0000]))


def test_order_is_case_insensitive() -> None:
    assert encode_uint32(1, "cdab") == [1, 0]


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: encode_int32(2**31), "int32"),
        (lambda: encode_int32(-(2**31) - 1), "int32"),
        (lambda: encode_uint32(-1), "uint32"),
        (lambda: encode_uint32(True), "uint32"),
        (lambda: encode_uint32(1, "ABDC"), "order"),
        (lambda: decode_uint32([1]), "2 registers"),
        (lambda: decode_uint32([1, 0x10000]), "65535"),
        (lambda: encode_float32("1.0"), "number"),  # type: ignore[arg-type]
        (lambda: decode_values("int32", [1, 2, 3]), "even"),
        (lambda: encode_values("int128", [1]), "kind"),
    ],
)
def test_bad_arguments(call: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()  # type: ignore[operator]


def test_float32_one_rule_for_range_nan_and_inf() -> None:
    # Out of range is a ValueError (like the integer encoders), not OverflowError.
    for value in (1e39, -1e39, 3.5e38, 10**400):
        with pytest.raises(ValueError, match="out of the float32 range"):
            encode_float32(value)
    # What a float32 can hold is written: the rounding edge, nan, the infinities.
    assert decode_float32(encode_float32(3.4028235e38)) == FLOAT32_MAX
    assert decode_float32(encode_float32(-3.4028235e38)) == -FLOAT32_MAX
    assert math.isnan(decode_float32(encode_float32(math.nan)))
    assert decode_float32(encode_float32(math.inf)) == math.inf


def test_many_values() -> None:
    regs = encode_values("int32", [1, -1, 70000], "CDAB")
    assert regs == [1, 0, 0xFFFF, 0xFFFF, 70000 & 0xFFFF, 1]
    assert decode_values("int32", regs, "CDAB") == [1, -1, 70000]
    assert decode_values("float32", encode_values("float32", [0.5, 2.0])) == [0.5, 2.0]


def test_strings() -> None:
    assert encode_string("CFW100") == [0x4346, 0x5731, 0x3030]
    assert encode_string("ABC") == [0x4142, 0x4300]
    assert encode_string("ABC", 4) == [0x4142, 0x4300, 0, 0]
    assert encode_string("AB", swap=True) == [0x4241]
    assert encode_string("A", 2, pad=b" ") == [0x4120, 0x2020]
    assert decode_string([0x4346, 0x5731, 0x3030, 0]) == "CFW100"
    assert decode_string([0x4241], swap=True) == "AB"
    assert decode_string([0x4120, 0x2020], strip=None) == "A   "
    assert decode_string(encode_string("V1.00", 5)) == "V1.00"
    with pytest.raises(ValueError, match="do not fit"):
        encode_string("ABCDE", 2)
    with pytest.raises(ValueError, match="65535"):
        decode_string([-1])
