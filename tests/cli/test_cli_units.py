"""The command line's pieces in process: argument types, exit codes, statistics,
value encoding and the sniffer's frame decoder."""

from __future__ import annotations

import argparse
from collections import Counter

import pytest

import pyrtu
from pyrtu.cli import COMMANDS, common, io, main, poll, scan, sniff
from pyrtu.pdu.errors import (
    BusFault,
    ExceptionResponseError,
    FrameError,
    ModbusError,
    NoResponseError,
    PortError,
)


def test_every_command_is_registered_in_order() -> None:
    names = ["read", "write", "poll", "scan", "info", "sniff", "simulate", "vbus", "demo"]
    names.append("bench")  # the users' benchmark suite (pyrtu.cli.bench)
    names.append("gateway")  # registered after the built-ins (pyrtu.cli.gateway)
    names.append("bridge")  # then the MQTT bridge (pyrtu.cli.bridge)
    names.append("template")  # the device templates (pyrtu.cli.template)
    assert list(COMMANDS) == names


@pytest.mark.parametrize(
    ("text", "seconds"),
    [("0.5", 0.5), ("500ms", 0.5), ("1750us", 0.00175), ("2s", 2.0), ("1e-3", 0.001)],
)
def test_seconds(text: str, seconds: float) -> None:
    assert common.seconds(text) == pytest.approx(seconds)


@pytest.mark.parametrize("text", ["", "fast", "-1", "1 min", "nan"])
def test_seconds_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        common.seconds(text)


def test_positive_seconds_and_parity() -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        common.positive_seconds("0")
    assert common.parity("e") == "E" and common.parity("even") == "E"
    for bad in ("evens", "Nonsense", "EN", ""):
        with pytest.raises(argparse.ArgumentTypeError, match="must be one of N, E, O, M, S"):
            common.parity(bad)


def test_exit_codes_of_errors() -> None:
    cases = [
        (PortError("/dev/x", "cannot open"), 3),
        (NoResponseError("nothing"), 4),
        (ExceptionResponseError(1, 3, 2), 5),
        (FrameError("crc"), 6),
        (BusFault("echo"), 6),
        (ModbusError("other"), 1),
        (FileNotFoundError(2, "No such file", "x.cap"), 3),
        (ValueError("bad"), 2),
        (KeyboardInterrupt(), 130),
        (RuntimeError("bug"), 1),
    ]
    for exc, code in cases:
        assert common.classify(exc) == code, exc
    assert set(common.EXIT_CODES) == {0, 1, 2, 3, 4, 5, 6, 130}
    doc = common.error_document(ExceptionResponseError(7, 16, 3), 5)
    assert (doc["error"], doc["exception_code"], doc["slave"]) == ("exception", 3, 7)


def test_jsonable() -> None:
    assert common.jsonable({1: [float("nan"), b"ok", (1.5,)]}) == {"1": ["nan", "ok", [1.5]]}


def test_address_range() -> None:
    assert scan.address_range("1-247") == range(1, 248)
    assert scan.address_range("5") == range(5, 6)
    for bad in ("0-5", "10-2", "1-248", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            scan.address_range(bad)


def test_percentile_and_poll_exit_status() -> None:
    assert poll.percentile([], 50) is None
    values = sorted(float(v) for v in range(1, 101))
    assert poll.percentile(values, 50) == 50.0
    assert poll.percentile(values, 99) == 99.0
    assert poll.percentile([7.0], 99) == 7.0
    assert poll.exit_status(Counter()) == 0
    assert poll.exit_status(Counter({"no_response": 1, "exception_2": 3})) == 5
    assert poll.exit_status(Counter({"frame": 2, "no_response": 1})) == 6
    assert poll.error_kind(ExceptionResponseError(1, 3, 4)) == "exception_4"
    assert poll.error_kind(ValueError()) is None


@pytest.mark.parametrize(
    ("kind", "order", "texts", "registers"),
    [
        ("uint16", "ABCD", ["0xFFFF"], [0xFFFF]),
        ("int16", "ABCD", ["-32768"], [0x8000]),
        ("int32", "ABCD", ["-2"], [0xFFFF, 0xFFFE]),
        ("float32", "DCBA", ["1.5"], [0x0000, 0xC03F]),
        ("string", "ABCD", ["AB", "C"], [0x4142, 0x2043]),
    ],
)
def test_encode_and_decode(kind: str, order: str, texts: list[str], registers: list[int]) -> None:
    regs, _ = io.encode(kind, texts, order)
    assert regs == registers
    decoded = io.decode(kind, regs, order)
    if kind == "string":
        assert decoded == [" ".join(texts)]
    else:
        assert decoded == [float(t) if kind == "float32" else int(t, 0) for t in texts]


@pytest.mark.parametrize(
    ("kind", "text", "hint"),
    [
        ("uint16", "-1", "--type int16"),
        ("int16", "40000", "-32768..32767"),
        ("float32", "x", "float32 value expected"),
    ],
)
def test_encode_refuses(kind: str, text: str, hint: str) -> None:
    with pytest.raises(ValueError, match=hint):
        io.encode(kind, [text], "ABCD")


def test_the_sniffers_decoder_pairs_requests_and_responses() -> None:
    d = sniff.Decoder("cfw701")

    def seen(kind: str, hexdata: str) -> sniff.Seen:
        message = bytes.fromhex(hexdata)
        return sniff.Seen(kind, message, pyrtu.add_crc(message), 0.0)

    req = d.decode(seen("request", "0103 02a8 0002"))
    assert req.fields == {"address": 680, "count": 2}
    resp = d.decode(seen("response", "0103 04 1700 1000"))
    assert resp.summary == "[680] 5888 [681] 4096"
    assert resp.notes[0].startswith("P680 status: running")
    coils = d.decode(seen("request", "020f 0010 000a 02 cd01"))
    assert coils.fields["values"] == [
        True,
        False,
        True,
        True,
        False,
        False,
        True,
        True,
        True,
        False,
    ]
    exc = d.decode(seen("exception", "0183 02"))
    assert exc.summary == "exception 2 (ILLEGAL DATA ADDRESS)"
    ident = d.decode(seen("response", "012b 0e01 8100 0002 0003 574547 0106 434657373031"))
    assert ident.fields["objects"] == {"0": "WEG", "1": "CFW701"}
    vendor = sniff.Decoder("acu")
    vendor.decode(seen("request", "0164 019b"))
    read32 = vendor.decode(seen("response", "0164 0000 0250"))
    assert read32.fields == {"value": 0x250, "address": 0x19B}
    assert read32.notes and read32.notes[0].startswith("411 status:")
    assert vendor.function_name(100) == "read_parameter_32"
    assert sniff.Decoder().function_name(100) == "function 0x64"


def test_main_in_process(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sniff", "--example", "--json"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 12 and '"type": "summary"' in lines[-1]
    assert main(["write", "/dev/null", "--table", "discrete", "0", "1"]) == 2
    assert "read-only" in capsys.readouterr().err
