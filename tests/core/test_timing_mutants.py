"""pyrtu.core.timing at every boundary the mutation run (docs/MUTATION.md) found
untested: the accepted ranges and types of each line parameter, the character and
silence times of Serial Line V1.02 2.5.1.1 (t1.5 and t3.5; 750 / 1750 us above
19200 baud, the WEG manuals' 860 / 2005 us), rounded to whole microseconds half
up as the C core's rtu_timing_init does, and the duration checks.  Expected values
computed here from the spec's formulas with `fractions`, not by the module."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest

from pyrtu.core._errtypes import ArgumentTypeError
from pyrtu.core.timing import (
    Timing,
    apply_overrides,
    bits_per_char,
    check_baudrate,
    check_bytesize,
    check_mode,
    check_parity,
    check_seconds,
    check_stopbits,
    check_timing,
    compute_timing,
    positive_seconds,
    seconds_to_us,
)


def _us(bits: int, baudrate: int, characters: Fraction) -> int:
    """``characters`` character times in microseconds, rounded half up."""
    exact = Fraction(bits * 1_000_000, baudrate) * characters
    return math.floor(exact + Fraction(1, 2))


@pytest.mark.parametrize("value", [50, 51, 9600, 3_999_999, 4_000_000])
def test_baud_rates_in_range(value: int) -> None:
    assert check_baudrate(value) == value


@pytest.mark.parametrize("value", [49, 0, -9600, 4_000_001])
def test_baud_rates_out_of_range(value: int) -> None:
    with pytest.raises(ValueError, match=r"^baudrate must be an integer 50\.\.4000000, not "):
        check_baudrate(value)


@pytest.mark.parametrize("value", [True, 9600.0, "9600", None])
def test_baud_rates_of_another_type(value: object) -> None:
    with pytest.raises(ArgumentTypeError, match="baudrate"):
        check_baudrate(value)


def test_timing_rules_and_modes() -> None:
    assert check_timing("modbus") == "modbus" and check_timing("weg") == "weg"
    assert check_mode("rtu") == "rtu" and check_mode("ascii") == "ascii"
    for bad in ("MODBUS", "", 1, None):
        with pytest.raises(ValueError, match="timing must be 'modbus' or 'weg'"):
            check_timing(bad)
        with pytest.raises(ValueError, match="mode must be 'rtu' or 'ascii'"):
            check_mode(bad)


@pytest.mark.parametrize(
    ("value", "letter"),
    [("N", "N"), ("e", "E"), (" odd ", "O"), ("Mark", "M"), ("space", "S"), ("NONE", "N")],
)
def test_parity_letters_and_names(value: str, letter: str) -> None:
    assert check_parity(value) == letter


def test_parity_refused() -> None:
    with pytest.raises(ValueError, match="parity must be one of N, E, O, M, S, not 'X'"):
        check_parity("X")
    with pytest.raises(ArgumentTypeError, match="parity"):
        check_parity(0)


def test_bytesize_and_stopbits() -> None:
    assert check_bytesize(7) == 7 and check_bytesize(8) == 8
    for bad in (6, 9):
        with pytest.raises(ValueError, match="bytesize must be 7 or 8"):
            check_bytesize(bad)
    for wrong in (True, 8.0, "8"):
        with pytest.raises(ArgumentTypeError, match="bytesize"):
            check_bytesize(wrong)
    assert [check_stopbits(v) for v in (1, 1.5, 2)] == [1, 1.5, 2]
    for bad in (0, 3, 2.5):
        with pytest.raises(ValueError, match=r"stopbits must be 1, 1\.5 or 2"):
            check_stopbits(bad)
    for wrong in (True, "1", None):
        with pytest.raises(ArgumentTypeError, match="stopbits"):
            check_stopbits(wrong)


@pytest.mark.parametrize(
    ("parity", "stopbits", "bytesize", "bits"),
    [
        ("E", 1, 8, 11),
        ("O", 1, 8, 11),
        ("N", 2, 8, 11),
        ("N", 1, 8, 10),
        ("E", 2, 8, 12),
        ("N", 1, 7, 9),
        ("E", 1, 7, 10),
    ],
)
def test_bits_per_character(parity: str, stopbits: float, bytesize: int, bits: int) -> None:
    """Start bit, data bits, the parity bit, stop bits (Serial Line V1.02 2.5.1)."""
    assert bits_per_char(parity, stopbits, bytesize) == bits


@pytest.mark.parametrize("baudrate", [50, 1200, 9600, 14400, 19200])
@pytest.mark.parametrize("bits", [7, 9, 10, 11, 12])
def test_up_to_19200_the_silences_are_1_5_and_3_5_characters(baudrate: int, bits: int) -> None:
    t = compute_timing(baudrate, bits)
    assert t.char_us == _us(bits, baudrate, Fraction(1))
    assert t.t15_us == _us(bits, baudrate, Fraction(3, 2))
    assert t.t35_us == _us(bits, baudrate, Fraction(7, 2))
    assert compute_timing(baudrate, bits, "weg") == t


@pytest.mark.parametrize("baudrate", [19201, 38400, 115200, 4_000_000])
def test_above_19200_the_silences_are_fixed(baudrate: int) -> None:
    modbus = compute_timing(baudrate, 11)
    assert (modbus.t15_us, modbus.t35_us) == (750, 1750)
    assert modbus.char_us == _us(11, baudrate, Fraction(1))
    weg = compute_timing(baudrate, 11, "weg")
    assert (weg.char_us, weg.t15_us, weg.t35_us) == (modbus.char_us, 860, 2005)


def test_a_half_microsecond_rounds_up() -> None:
    # 10 bits at 32000 baud: 312.5 us; at 1600 baud t1.5 = 9375 us exactly
    assert compute_timing(32000, 10).char_us == 313
    assert compute_timing(1600, 10).t15_us == 9375
    # 10 bits at 64000 baud: 156.25 us, down
    assert compute_timing(64000, 10).char_us == 156


@pytest.mark.parametrize("bits", [6, 13])
def test_bits_per_character_out_of_range(bits: int) -> None:
    with pytest.raises(ValueError, match=f"bits per character must be 7..12, not {bits}"):
        compute_timing(9600, bits)


def test_compute_timing_checks_its_arguments() -> None:
    with pytest.raises(ValueError, match="baudrate"):
        compute_timing(49, 11)
    with pytest.raises(ValueError, match="timing must be"):
        compute_timing(9600, 11, "fast")


def test_timing_in_seconds() -> None:
    t = Timing(1146, 1719, 4010)
    assert (t.char, t.t15, t.t35) == (0.001146, 0.001719, 0.00401)


def test_seconds_to_microseconds() -> None:
    assert seconds_to_us(0, "t35") == 0
    assert seconds_to_us(0.0035, "t35") == 3500
    assert seconds_to_us(1, "t35") == 1_000_000
    for bad in (-1e-9, math.nan, math.inf):
        with pytest.raises(ValueError, match=r"^t35 must be a non-negative number of seconds"):
            seconds_to_us(bad, "t35")
    for wrong in (True, "1"):
        with pytest.raises(ArgumentTypeError, match=r"^t15 must be"):
            seconds_to_us(wrong, "t15")  # type: ignore[arg-type]


def test_check_seconds_bounds() -> None:
    assert check_seconds("timeout", 0) == 0.0 and type(check_seconds("timeout", 1)) is float
    assert positive_seconds(1e-9, "timeout") == 1e-9
    with pytest.raises(ValueError, match=r"^timeout must be a positive number of seconds, not 0$"):
        positive_seconds(0, "timeout")
    for bad in (-1e-9, math.inf, math.nan):
        with pytest.raises(ValueError, match=r"^delay must be a non-negative number of seconds"):
            check_seconds("delay", bad)
        with pytest.raises(ValueError, match=r"^timeout must be a positive number"):
            positive_seconds(bad, "timeout")
    for wrong in (True, "1", None):
        with pytest.raises(ArgumentTypeError, match=r"^delay must be a non-negative"):
            check_seconds("delay", wrong)


def test_overrides() -> None:
    base = Timing(1146, 1719, 4010)
    assert apply_overrides(base, None, None) == base
    assert apply_overrides(base, 0.002, None) == Timing(1146, 2000, 4010)
    assert apply_overrides(base, None, 0.005) == Timing(1146, 1719, 5000)


def test_a_timing_is_immutable_and_hashable() -> None:
    import dataclasses

    t = Timing(1146, 1719, 4010)
    assert hash(t) == hash(compute_timing(9600, 11))
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.char_us = 1  # type: ignore[misc]


def test_the_default_character_format_is_8e1() -> None:
    """Serial Line V1.02 2.5.1: an RTU character is 8 data bits with even parity by
    default and one stop bit: start + 8 + parity + stop = 11 bits."""
    assert bits_per_char() == 11
    assert bits_per_char("E") == bits_per_char("E", 1) == bits_per_char("E", 1, 8) == 11
