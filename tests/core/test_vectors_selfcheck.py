"""Self-check of tests/vectors.py against local reference CRC/LRC functions.

Deliberately independent of pyrtu: the package is checked *with* these vectors, so
the vectors must not be checked with the package.
"""

from collections import Counter

import pytest
from vectors import ASCII, RTU, TELEGRAMS, Telegram, crc_bitwise

# Telegrams per manual, (rtu, ascii). Determined by reading the manuals; see the
# docstring of tests/vectors.py. A change here must come with a reason.
EXPECTED_COUNTS: dict[str, tuple[int, int]] = {
    "CFW100": (10, 0),
    "CFW320": (0, 0),  # the CFW320 manual prints no telegrams
    "CFW701": (4, 0),
    "CV100": (20, 2),
    "ACT/ACU": (22, 19),
}
SOURCES = set(EXPECTED_COUNTS)
KINDS = {"request", "response", "exception"}


#: CRC-16/MODBUS, bit by bit: init 0xFFFF, reflected polynomial 0xA001.
ref_crc16 = crc_bitwise


def ref_lrc(data: bytes) -> int:
    """Two's complement of the 8-bit sum."""
    return -sum(data) & 0xFF


def ascii_binary(frame: bytes) -> bytes:
    """Address, function, data and LRC of an ASCII frame, as binary bytes."""
    assert frame.startswith(b":") and frame.endswith(b"\r\n")
    return bytes.fromhex(frame[1:-2].decode("ascii"))


def pdu_of(t: Telegram) -> bytes:
    """Address, function and data (no CRC/LRC) of either mode."""
    return t.adu[:-2] if t.mode == "rtu" else ascii_binary(t.adu)[:-1]


def tid(t: Telegram) -> str:
    return f"{t.source}:{t.mode}:{t.kind}:{t.where[:40]}"


# --------------------------------------------------------------- reference functions


def test_ref_crc16_check_value() -> None:
    assert ref_crc16(b"123456789") == 0x4B37


def test_ref_crc16_of_frame_with_crc_is_zero() -> None:
    body = b"\x01\x03\x00\x00\x00\x0a"
    crc = ref_crc16(body)
    assert ref_crc16(body + bytes([crc & 0xFF, crc >> 8])) == 0


def test_ref_lrc_manual_worked_example() -> None:
    # Bonfiglioli 6.7.2.3: 0x01 + 0x83 + 0x02 = 134, two's complement 122 = 0x7A
    assert ref_lrc(b"\x01\x83\x02") == 0x7A
    assert ref_lrc(b"") == 0
    assert ref_lrc(b"\x80\x80") == 0


# ------------------------------------------------------------------- per telegram


@pytest.mark.parametrize("t", RTU, ids=tid)
def test_rtu_crc(t: Telegram) -> None:
    assert 4 <= len(t.adu) <= 256
    crc = ref_crc16(t.adu[:-2])
    assert t.adu[-2:] == bytes([crc & 0xFF, crc >> 8]), (
        f"computed CRC bytes {crc & 0xFF:02X} {crc >> 8:02X}"
    )
    assert ref_crc16(t.adu) == 0


@pytest.mark.parametrize("t", ASCII, ids=tid)
def test_ascii_lrc_and_framing(t: Telegram) -> None:
    frame = t.adu
    assert frame[:1] == b":" and frame[-2:] == b"\r\n"
    body = frame[1:-2]
    assert len(body) % 2 == 0 and len(body) >= 6
    assert all(c in b"0123456789ABCDEF" for c in body), "upper-case hex only"
    binary = ascii_binary(frame)
    assert binary[-1] == ref_lrc(binary[:-1]), f"computed LRC {ref_lrc(binary[:-1]):02X}"
    # re-encoding gives the same frame
    rebuilt = b":" + binary[:-1].hex().upper().encode() + b"%02X\r\n" % ref_lrc(binary[:-1])
    assert rebuilt == frame


@pytest.mark.parametrize("t", TELEGRAMS, ids=tid)
def test_metadata(t: Telegram) -> None:
    assert t.source in SOURCES
    assert t.mode in ("rtu", "ascii")
    assert t.kind in KINDS
    assert t.where.strip()
    pdu = pdu_of(t)
    assert 1 <= pdu[0] <= 247, "no broadcasts among the examples"
    is_exc = bool(pdu[1] & 0x80)
    assert is_exc == (t.kind == "exception")
    if is_exc:
        assert len(pdu) == 3 and 1 <= pdu[2] <= 4


# ------------------------------------------------------------------ the collection


def test_counts_per_source() -> None:
    got = {s: (0, 0) for s in SOURCES}
    for t in TELEGRAMS:
        rtu, asc = got[t.source]
        got[t.source] = (rtu + 1, asc) if t.mode == "rtu" else (rtu, asc + 1)
    assert got == EXPECTED_COUNTS
    assert len(TELEGRAMS) == 77
    assert len(RTU) == 56 and len(ASCII) == 21


def test_rtu_ascii_partition() -> None:
    assert RTU + ASCII == tuple(t for t in TELEGRAMS if t.mode == "rtu") + tuple(
        t for t in TELEGRAMS if t.mode == "ascii"
    )
    assert set(RTU) | set(ASCII) == set(TELEGRAMS)


def test_no_duplicate_entries() -> None:
    keys = Counter((t.source, t.where, t.mode, t.kind) for t in TELEGRAMS)
    assert [k for k, n in keys.items() if n > 1] == []


def _check_pairs(telegrams: tuple[Telegram, ...]) -> list[Telegram]:
    """Every reply directly follows its request; return the standalone replies."""
    standalone = []
    for i, t in enumerate(telegrams):
        if t.kind == "request":
            continue
        prev = telegrams[i - 1] if i else None
        if (
            prev is not None
            and prev.kind == "request"
            and prev.source == t.source
            and prev.where == t.where
        ):
            p, q = pdu_of(prev), pdu_of(t)
            assert q[0] == p[0] and q[1] & 0x7F == p[1], tid(t)
        else:
            standalone.append(t)
    return standalone


def test_rtu_pairs_adjacent() -> None:
    assert _check_pairs(RTU) == []
    # and every RTU request is answered by the next telegram
    for i, t in enumerate(RTU):
        if t.kind == "request":
            assert RTU[i + 1].kind != "request", tid(t)


def test_ascii_pairs_adjacent() -> None:
    standalone = _check_pairs(ASCII)
    assert [t.where for t in standalone] == [
        "6.7.2.3 LRC Checking, example: exception response 01 83 02"
    ]
    for i, t in enumerate(ASCII):
        if t.kind == "request":
            assert ASCII[i + 1].kind != "request", tid(t)


def test_write_single_echo() -> None:
    """FC 06 and Bonfiglioli FC 101 responses are echoes of the request."""
    for i, t in enumerate(TELEGRAMS):
        if t.kind == "response" and pdu_of(t)[1] in (0x06, 0x65):
            assert TELEGRAMS[i - 1].adu == t.adu, tid(t)


def test_act_ascii_matches_rtu_examples() -> None:
    """Bonfiglioli 8.2 repeats 8.1 in ASCII (8.2.4, FC 101, is missing from the text)."""
    rtu = [pdu_of(t) for t in RTU if t.source == "ACT/ACU" and t.adu[1] & 0x7F != 0x65]
    asc = [pdu_of(t) for t in ASCII if t.source == "ACT/ACU" and t.where.startswith("8.2")]
    assert asc == rtu
    lrc_example = [t for t in ASCII if t.where.startswith("6.7.2.3")]
    assert [pdu_of(t) for t in lrc_example] == [b"\x01\x83\x02"]


# ------------------------------------------------------------------------- errata


def _find(source: str, mode: str, kind: str, where_part: str) -> list[Telegram]:
    return [
        t
        for t in TELEGRAMS
        if t.source == source and t.mode == mode and t.kind == kind and where_part in t.where
    ]


@pytest.mark.parametrize("source", ["CFW100", "CFW701"])
def test_erratum_fc43_request_crc(source: str) -> None:
    (t,) = _find(source, "rtu", "request", "Function 43")
    assert t.adu == bytes.fromhex("01 2B 0E 01 02 F1 B6")
    assert "erratum" in t.note and "70 77" in t.note and "F1 B6" in t.note
    # the printed CRC belongs to object 00h
    assert ref_crc16(bytes.fromhex("01 2B 0E 01 00")) == 0x7770


def test_erratum_cv100_deceleration_response() -> None:
    (t,) = _find("CV100", "rtu", "response", "deceleration time")
    assert t.adu == bytes.fromhex("05 03 02 00 3C 49 95")
    assert "erratum" in t.note and "344F" in t.note and "49 95" in t.note
    (req,) = _find("CV100", "rtu", "request", "deceleration time")
    assert req.adu[-2:] == bytes.fromhex("34 4F")  # where the printed checksum came from


def test_erratum_act_ascii_fc100_exception() -> None:
    (t,) = _find("ACT/ACU", "ascii", "exception", "8.2.3")
    assert t.adu == b":01E40417\r\n"
    assert "erratum" in t.note and "0 1 E 4 0 2 1 9" in t.note and "17" in t.note
    (rtu,) = _find("ACT/ACU", "rtu", "exception", "8.1.3")
    assert pdu_of(rtu) == pdu_of(t) == b"\x01\xe4\x04"


def test_uncorrected_errata_absent() -> None:
    wrong = {
        bytes.fromhex("01 2B 0E 01 02 70 77"),
        bytes.fromhex("05 03 02 00 3C 34 4F"),
        b":01E40219\r\n",
    }
    assert not wrong & {t.adu for t in TELEGRAMS}


def test_every_erratum_is_noted() -> None:
    noted = [t for t in TELEGRAMS if "erratum" in t.note]
    assert len(noted) == 4  # FC 43 in two manuals, CV100, Bonfiglioli ASCII
