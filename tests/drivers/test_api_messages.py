"""Bad arguments at the API get TypeError for a wrong type and ValueError for a wrong
value, with a message naming the argument, and nothing is sent (issue 9, item 9)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from types import ModuleType

import pytest
from ptylink import PtyLink

from pyrtu import pdu as pdus
from pyrtu.drivers.master import Master

WRONG_TYPES: list[tuple[Callable[[], object], str]] = [
    # the values were iterated or read as numbers: "'int' object is not iterable",
    # and b"ab" wrote the registers 97 and 98
    (lambda: pdus.write_registers_request(0, 5), "write_registers: values must be a sequence"),
    (lambda: pdus.write_registers_request(0, b"ab"), "values must be a sequence .* not bytes"),
    (lambda: pdus.write_registers_request(0, bytearray(b"ab")), "not bytearray"),
    (lambda: pdus.write_registers_request(0, memoryview(b"ab")), "not memoryview"),
    (lambda: pdus.write_registers_request(0, "12"), "not str"),
    (lambda: pdus.write_registers_request(0, [1.0]), r"values\[0\] must be an integer"),
    (lambda: pdus.write_registers_request(0, None), "values must be a sequence"),  # type: ignore[arg-type]
    (lambda: pdus.write_coils_request(0, b"\x01\x00"), "write_coils: values .* not bytes"),
    (lambda: pdus.write_coils_request(0, 1), "write_coils: values must be a sequence"),  # type: ignore[arg-type]
    (lambda: pdus.write_coils_request(0, [None]), r"values\[0\] must be a bool"),
    (lambda: pdus.read_write_request(0, 1, 0, b"ab"), "read_write_registers: values"),
    (lambda: pdus.read_file_request(5), "read_file_record: items must be a sequence"),  # type: ignore[arg-type]
    (lambda: pdus.read_file_request([5]), "item 0 must be"),  # type: ignore[list-item]
    (lambda: pdus.write_file_request([(1, 0, b"ab")]), "write_file_record: values .* bytes"),
    (lambda: pdus.read_request(3, 1.0, 1), "address must be an integer"),  # type: ignore[arg-type]
    (lambda: pdus.read_request(3, 0, True), "count must be an integer"),
    (lambda: pdus.check_slave("x", "1", broadcast=False), "slave must be an integer"),
]


@pytest.mark.parametrize(("call", "message"), WRONG_TYPES)
def test_wrong_types_raise_type_error(call: Callable[[], object], message: str) -> None:
    with pytest.raises(TypeError, match=message) as info:
        call()
    # also a ValueError, for code written when every bad argument raised ValueError
    assert isinstance(info.value, ValueError)


WRONG_VALUES: list[tuple[Callable[[], object], str]] = [
    (lambda: pdus.write_coils_request(0, [2]), r"values\[0\] must be a bool"),
    (lambda: pdus.write_registers_request(0, [70000]), r"values\[0\] must be 0..65535"),
    (lambda: pdus.read_file_request([(1, 2)]), "item 0 must be"),  # type: ignore[list-item]
]


@pytest.mark.parametrize(("call", "message"), WRONG_VALUES)
def test_wrong_values_raise_value_error(call: Callable[[], object], message: str) -> None:
    with pytest.raises(ValueError, match=message) as info:
        call()
    assert not isinstance(info.value, TypeError)


def test_sequences_of_any_kind_are_accepted() -> None:
    want = pdus.write_registers_request(0, [97, 98])
    assert pdus.write_registers_request(0, (97, 98)) == want
    assert pdus.write_registers_request(0, iter([97, 98])) == want
    assert pdus.write_registers_request(0, range(97, 99)) == want
    assert pdus.write_coils_request(0, (True, 0, 1)) == pdus.write_coils_request(0, [1, 0, 1])


@pytest.fixture
def link() -> Iterator[PtyLink]:
    with PtyLink() as pty:
        yield pty


def test_master_refuses_before_sending(link: PtyLink) -> None:
    with Master(link.path_a, parity="N", t35=0, timeout=0.2) as m:
        with pytest.raises(TypeError, match="write_registers: values"):
            m.write_registers(1, 0, 5)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="not bytes"):
            m.write_registers(1, 0, b"ab")
        with pytest.raises(TypeError, match="write_coils: values"):
            m.write_coils(1, 0, "10")
        link.settle()
        assert link.wire("a") == b""
        assert m.counters["requests"] == 0


def test_frame_list_index_types(backend: ModuleType) -> None:
    frames = backend.parse_stream(backend.add_crc(bytes.fromhex("0103000a0002")) * 2)
    assert frames[True] == frames[1]  # like a list: bool is an int
    for bad in ("a", 1.0, None, (0,)):
        with pytest.raises(TypeError, match="FrameList indices must be integers or slices"):
            frames[bad]
    with pytest.raises(IndexError):
        frames[2]


# The line options (the framer, parse_stream, char_timing, LineConfig): a wrong type is
# a TypeError on both backends (it was ValueError, and parity=5 an AttributeError).
LINE_WRONG_TYPES: list[tuple[dict[str, object], str]] = [
    ({"parity": 5}, "parity must be one of"),
    ({"baudrate": "9600"}, "baudrate must be an integer 50..4000000"),
    ({"baudrate": 9600.0}, "baudrate must be an integer 50..4000000"),
    ({"bytesize": "8"}, "bytesize must be 7 or 8"),
    ({"stopbits": "1"}, "stopbits must be 1, 1.5 or 2"),
    ({"max_adu": "256"}, "max_adu must be"),
    ({"t35": "0.002"}, "t35 must be a non-negative number of seconds"),
    ({"rules": {"3": (None, None)}}, "function code must be 1..127"),
    ({"rules": {3: [None, None]}}, r"rules\[3\]: give \(request_rule, response_rule\)"),
    ({"rules": {3: (5, None)}}, r"rules\[3\]: 5 is not a LengthRule"),
]


@pytest.mark.parametrize(("options", "message"), LINE_WRONG_TYPES)
def test_line_options_of_the_wrong_type(
    backend: ModuleType, options: dict[str, object], message: str
) -> None:
    from pyrtu import LineConfig

    for make in (
        lambda: backend.Framer("master", **options),
        lambda: backend.parse_stream(b"", **options),
        lambda: LineConfig(**options),  # type: ignore[arg-type]
    ):
        with pytest.raises(TypeError, match=message) as info:
            make()
        assert isinstance(info.value, ValueError)  # still caught by `except ValueError`


def test_line_options_of_the_wrong_value_stay_value_errors(backend: ModuleType) -> None:
    for options in ({"parity": "X"}, {"baudrate": 0}, {"bytesize": 6}, {"max_adu": 3}):
        with pytest.raises(ValueError) as info:
            backend.Framer("master", **options)
        assert not isinstance(info.value, TypeError), options
