"""PDUs: exact bytes, argument checks, parsers, slave-side decoders and their codes."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from pyrtu import pdu as pdus
from pyrtu.pdu.errors import FrameError, SlaveException


def test_request_bytes() -> None:
    # CFW100 6.1 / 6.2 / 6.3, CV100 and ACT/ACU examples (PDU part of the telegrams)
    assert pdus.read_request(3, 2, 2) == bytes.fromhex("03 0002 0002")
    assert pdus.write_register_request(0x02AB, 0x1000) == bytes.fromhex("06 02AB 1000")
    assert pdus.write_registers_request(100, [10, 20]) == bytes.fromhex("10 0064 0002 04 000A 0014")
    assert pdus.diagnostics_request(0x0A) == bytes.fromhex("08 000A 0000")
    assert pdus.device_id_request(1, 2) == bytes.fromhex("2B 0E 01 02")
    # Application Protocol examples
    assert pdus.read_request(1, 19, 19) == bytes.fromhex("01 0013 0013")
    assert pdus.write_coil_request(172, True) == bytes.fromhex("05 00AC FF00")
    assert pdus.write_coil_request(172, 0) == bytes.fromhex("05 00AC 0000")
    assert pdus.write_coils_request(19, [1, 0, 1, 1, 0, 0, 1, 1, 1, 0]) == bytes.fromhex(
        "0F 0013 000A 02 CD 01"
    )
    assert pdus.mask_write_request(4, 0xF2, 0x25) == bytes.fromhex("16 0004 00F2 0025")
    assert pdus.read_write_request(3, 6, 14, [0xFF, 0xFF, 0xFF]) == bytes.fromhex(
        "17 0003 0006 000E 0003 06 00FF 00FF 00FF"
    )
    assert pdus.fifo_request(0x04DE) == bytes.fromhex("18 04DE")
    assert pdus.read_file_request([(4, 1, 2), (3, 9, 2)]) == bytes.fromhex(
        "14 0E 06 0004 0001 0002 06 0003 0009 0002"
    )
    assert pdus.write_file_request([(4, 7, [0x06AF, 0x04BE, 0x100D])]) == bytes.fromhex(
        "15 0D 06 0004 0007 0003 06AF 04BE 100D"
    )


BAD: list[tuple[Callable[[], object], str]] = [
    (lambda: pdus.read_request(1, 0, 0), "count must be 1..2000"),
    (lambda: pdus.read_request(2, 0, 2001), "count must be 1..2000"),
    (lambda: pdus.read_request(3, 0, 126), "count must be 1..125"),
    (lambda: pdus.read_request(4, -1, 1), "address must be 0..65535"),
    (lambda: pdus.read_request(3, 65535, 2), "runs past 65535"),
    (lambda: pdus.read_request(3, 1.0, 1), "must be an integer"),  # type: ignore[arg-type]
    (lambda: pdus.read_request(3, 0, True), "must be an integer"),
    (lambda: pdus.write_register_request(0, 65536), "value must be 0..65535"),
    (lambda: pdus.write_coil_request(0, 2), "bool"),
    (lambda: pdus.write_coils_request(0, [True] * 1969), "1..1968"),
    (lambda: pdus.write_coils_request(0, []), "1..1968"),
    (lambda: pdus.write_registers_request(0, [0] * 124), "1..123"),
    (lambda: pdus.write_registers_request(65500, [0] * 100), "runs past"),
    (lambda: pdus.write_registers_request(0, [1, -1]), r"values\[1\]"),
    (lambda: pdus.mask_write_request(0, 0x10000, 0), "and_mask"),
    (lambda: pdus.read_write_request(0, 126, 0, [1]), "read_count must be 1..125"),
    (lambda: pdus.read_write_request(0, 1, 0, [1] * 122), "1..121"),
    (lambda: pdus.diagnostics_request(0x10000), "sub_function"),
    (lambda: pdus.diagnostics_request(0, -1), "data"),
    (lambda: pdus.fifo_request(70000), "address"),
    (lambda: pdus.read_file_request([]), "at least one"),
    (lambda: pdus.read_file_request([(0, 1, 1)]), "file must be 1..65535"),
    (lambda: pdus.read_file_request([(1, 10000, 1)]), "record must be 0..9999"),
    (lambda: pdus.read_file_request([(1, 0, 100)] * 3), "would not fit"),
    (lambda: pdus.read_file_request([(1, 2)]), "must be"),  # type: ignore[list-item]
    (lambda: pdus.write_file_request([(1, 0, [0] * 130)]), "number of values"),
    (lambda: pdus.device_id_request(5, 0), "read_code must be 1..4"),
    (lambda: pdus.device_id_request(1, 256), "object_id"),
    (lambda: pdus.check_slave("x", 248, broadcast=True), "slave must be 0..247"),
    (lambda: pdus.check_slave("x", 0, broadcast=False), "broadcast"),
]


@pytest.mark.parametrize(("call", "message"), BAD)
def test_argument_checks(call: Callable[[], object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()


def test_bits_packing() -> None:
    bits = [True, False, True, True, False, False, True, True, True, False]
    assert pdus.pack_bits(bits) == b"\xcd\x01"
    assert pdus.unpack_bits(b"\xcd\x01", 10) == bits


def test_parsers_accept_answers() -> None:
    assert pdus.parse_registers(bytes.fromhex("03 04 001E 000F"), 2) == [30, 15]
    assert pdus.parse_bits(bytes.fromhex("01 03 CD 6B 05"), 19)[:3] == [True, False, True]
    pdus.parse_echo(bytes.fromhex("06 02AB 1000"), bytes.fromhex("06 02AB 1000"))
    pdus.parse_echo(bytes.fromhex("10 0064 0002"), bytes.fromhex("10 0064 0002 04 000A 0014"), 5)
    assert pdus.parse_diagnostics(bytes.fromhex("08 000E 0001"), 0x0E) == 1
    assert pdus.parse_event_counter(bytes.fromhex("0B FFFF 0108")) == (0xFFFF, 0x108)
    log = pdus.parse_event_log(bytes.fromhex("0C 08 0000 0108 0121 20 00"))
    assert log == pdus.CommEventLog(0, 0x108, 0x121, [0x20, 0x00])
    assert pdus.parse_fifo(bytes.fromhex("18 0006 0002 01B8 1284")) == [0x1B8, 0x1284]
    assert pdus.parse_read_file(
        bytes.fromhex("14 0C 05 06 0DFE 0020 05 06 33CD 0040"), [(4, 1, 2), (3, 9, 2)]
    ) == [[0x0DFE, 0x20], [0x33CD, 0x40]]
    assert pdus.parse_server_id(bytes.fromhex("11 03 41 42 FF")) == b"AB\xff"
    assert pdus.parse_exception_status(bytes.fromhex("07 6D")) == 0x6D
    page = pdus.parse_device_id(bytes.fromhex("2B 0E 01 81 00 00 01 02 05 56312E3030"), 1)
    assert page == pdus.DeviceIdPage(1, 0x81, False, 0, [(2, b"V1.00")])


REJECTED: list[tuple[Callable[[], object], str]] = [
    (lambda: pdus.parse_registers(bytes.fromhex("03 02 0001"), 2), "expected 6"),
    (
        lambda: pdus.parse_registers(bytes.fromhex("03 06 0001 0002"), 2),
        "PDU has 6 bytes|byte count",
    ),
    (lambda: pdus.parse_bits(bytes.fromhex("01 02 CD"), 9), "expected 4"),
    (lambda: pdus.parse_echo(b"\x06\x00\x01\x00\x02", b"\x06\x00\x01\x00\x03"), "does not echo"),
    (lambda: pdus.parse_diagnostics(bytes.fromhex("08 000B 0001"), 0x0E), "sub-function"),
    (lambda: pdus.parse_event_log(bytes.fromhex("0C 09 0000 0108 0121 20")), "malformed"),
    (lambda: pdus.parse_fifo(bytes.fromhex("18 0006 0003 01B8 1284")), "FIFO count"),
    (lambda: pdus.parse_read_file(bytes.fromhex("14 04 05 06 0DFE"), [(4, 1, 2)]), "malformed"),
    (lambda: pdus.parse_device_id(bytes.fromhex("2B 0E 02 81 00 00 00"), 1), "read code"),
    (lambda: pdus.parse_device_id(bytes.fromhex("2B 0E 01 81 01 00 00"), 1), "More Follows"),
    (lambda: pdus.parse_device_id(bytes.fromhex("2B 0E 01 81 00 00 01 02 09 41"), 1), "runs past"),
    (lambda: pdus.parse_server_id(bytes.fromhex("11 05 41")), "byte count"),
]


@pytest.mark.parametrize(("call", "message"), REJECTED)
def test_parsers_reject_malformed(call: Callable[[], object], message: str) -> None:
    with pytest.raises(FrameError, match=message) as info:
        call()
    assert isinstance(info.value, ValueError)


def test_slave_decoders_round_trip() -> None:
    assert pdus.decode_read(pdus.read_request(3, 10, 125)) == (10, 125)
    assert pdus.decode_write_single(pdus.write_coil_request(5, True)) == (5, 0xFF00)
    assert pdus.decode_write_coils(pdus.write_coils_request(3, [True, False, True])) == (
        3,
        [True, False, True],
    )
    assert pdus.decode_write_registers(pdus.write_registers_request(7, [1, 2])) == (7, [1, 2])
    assert pdus.decode_mask_write(pdus.mask_write_request(4, 0xF2, 0x25)) == (4, 0xF2, 0x25)
    assert pdus.decode_read_write(pdus.read_write_request(3, 6, 14, [1, 2])) == (3, 6, 14, [1, 2])
    assert pdus.decode_diagnostics(pdus.diagnostics_request(0x0E)) == (0x0E, 0)
    assert pdus.decode_fifo(pdus.fifo_request(0x4DE)) == 0x4DE
    assert pdus.decode_read_file(pdus.read_file_request([(4, 1, 2)])) == [(4, 1, 2)]
    assert pdus.decode_write_file(pdus.write_file_request([(4, 7, [1, 2])])) == [(4, 7, [1, 2])]
    assert pdus.decode_device_id(pdus.device_id_request(4, 0x81)) == (4, 0x81)


SLAVE_CODES: list[tuple[str, int]] = [
    ("03 0000 0000", 3),  # quantity 0
    ("03 0000 007E", 3),  # 126 registers
    ("01 0000 07D1", 3),  # 2001 coils
    ("03 FFFF 0002", 2),  # runs past 0xFFFF
    ("03 0000", 3),  # too short
    ("05 0000 1234", 3),  # neither ON nor OFF
    ("0F 0000 000A 01 FF", 3),  # byte count 1 for 10 coils
    ("10 0000 0002 03 000100", 3),  # byte count 3 for 2 registers
    ("10 FFFF 0002 04 00010002", 2),
    ("17 0000 0001 0000 007A F4", 3),  # 122 registers written
    ("14 07 06 0001 0000 0001 00", 3),  # byte count does not match
    ("14 07 05 0001 0000 0001", 2),  # reference type 5
    ("14 07 06 0000 0000 0001", 2),  # file 0
    ("2B 0D 01 00", 1),  # MEI type 13
    ("2B 0E 05 00", 3),  # read code 5
]


@pytest.mark.parametrize(("hexpdu", "expected"), SLAVE_CODES)
def test_slave_decoders_codes(hexpdu: str, expected: int) -> None:
    pdu = bytes.fromhex(hexpdu)
    decoder = {
        1: pdus.decode_read,
        3: pdus.decode_read,
        5: pdus.decode_write_single,
        15: pdus.decode_write_coils,
        16: pdus.decode_write_registers,
        23: pdus.decode_read_write,
        20: pdus.decode_read_file,
        43: pdus.decode_device_id,
    }[pdu[0]]
    with pytest.raises(SlaveException) as info:
        decoder(pdu)
    assert info.value.code == expected


def test_slave_encoders() -> None:
    assert pdus.registers_response(3, [30, 15]) == bytes.fromhex("03 04 001E 000F")
    assert pdus.bits_response(1, [True] * 9) == bytes.fromhex("01 02 FF 01")
    assert pdus.exception_response(6, 2) == bytes.fromhex("86 02")
    assert pdus.fifo_response([0x1B8, 0x1284]) == bytes.fromhex("18 0006 0002 01B8 1284")
    assert pdus.read_file_response([[0x0DFE, 0x20]]) == bytes.fromhex("14 06 05 06 0DFE 0020")
    page = pdus.DeviceIdPage(1, 0x81, True, 2, [(0, b"WEG")])
    assert pdus.device_id_response(page) == bytes.fromhex("2B 0E 01 81 FF 02 01 00 03 574547")
    done = pdus.DeviceIdPage(1, 0x81, False, 7, [])
    assert pdus.device_id_response(done)[4:6] == b"\x00\x00"  # Next Object is 0 when done
