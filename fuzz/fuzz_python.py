"""atheris harness for the Python layer (issue 9): the PDU decoders and parsers, and
parse_stream / Framer on the C core and the pure-Python twin side by side.

    python fuzz/fuzz_python.py -max_total_time=60 build/fuzz/corpus/python

Invariants: a request decoder (the slave side) raises only SlaveException, a response
parser (the master side) only FrameError, for any bytes; parse_stream and the Framer
give the same events, counters and exceptions on both backends, frames carry a valid
CRC and the events tile the input.  ``make fuzz-python`` installs atheris (PyPI) and
runs this for FUZZ_SECONDS.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import atheris

with atheris.instrument_imports():
    import pyrtu
    from pyrtu.pdu import base, client
    from pyrtu.pdu.errors import FrameError, SlaveException

C = pyrtu.backend("c")
PY = pyrtu.backend("python")

#: each decoder with the function codes the slave hands it (it dispatches on pdu[0])
DECODERS: list[tuple[Callable[[bytes], object], tuple[int, ...]]] = [
    (base.decode_read, (1, 2, 3, 4)),
    (base.decode_write_single, (5, 6)),
    (base.decode_write_coils, (15,)),
    (base.decode_write_registers, (16,)),
    (base.decode_mask_write, (22,)),
    (base.decode_read_write, (23,)),
    (base.decode_diagnostics, (8,)),
    (base.decode_fifo, (24,)),
    (base.decode_read_file, (20,)),
    (base.decode_write_file, (21,)),
    (base.decode_device_id, (43,)),
]


def _parsers(fdp: Any) -> list[Callable[[bytes], object]]:
    count = fdp.ConsumeIntInRange(1, 2000)
    items = [(1, fdp.ConsumeIntInRange(0, 9999), fdp.ConsumeIntInRange(1, 60))]
    # what the master sent: a request PDU of at least function + address + value
    request = fdp.ConsumeBytes(8).ljust(5, b"\x00")
    return [
        lambda pdu: client.parse_bits(pdu, count),
        lambda pdu: client.parse_registers(pdu, min(count, 125)),
        lambda pdu: client.parse_echo(pdu, request),
        lambda pdu: client.parse_echo(pdu, request, 5),
        client.parse_exception_status,
        lambda pdu: client.parse_diagnostics(pdu, count & 0xFFFF),
        client.parse_event_counter,
        client.parse_event_log,
        client.parse_server_id,
        client.parse_fifo,
        lambda pdu: client.parse_read_file(pdu, items),
        lambda pdu: client.parse_device_id(pdu, 1 + count % 4),
    ]


def _pdu_layer(fdp: Any) -> None:
    parsers = _parsers(fdp)
    # a PDU always has its function code: the slave and the master dispatch on it first
    pdu = bytes((fdp.ConsumeIntInRange(0, 255),)) + fdp.ConsumeBytes(fdp.ConsumeIntInRange(0, 300))
    for decode, codes in DECODERS:
        try:
            decode(bytes((codes[pdu[0] % len(codes)],)) + pdu[1:])
        except SlaveException:
            pass
    for parse in parsers:
        try:
            parse(pdu)
        except FrameError:
            pass


def _outcome(fn: Callable[[], object]) -> tuple[str, object]:
    try:
        return ("ok", fn())
    except (TypeError, ValueError) as exc:
        return ("raise", type(exc))


def _events(frames: Any) -> list[tuple[object, ...]]:
    return [(f.kind, f.adu, f.offset, f.error, f.start, f.end) for f in frames]


def _stream(fdp: Any) -> None:
    role = ("master", "slave", "monitor")[fdp.ConsumeIntInRange(0, 2)]
    strict = fdp.ConsumeBool()
    max_adu = fdp.ConsumeIntInRange(3, 1025)
    n_chunks = fdp.ConsumeIntInRange(0, 8)
    raw_chunks = [
        (fdp.ConsumeIntInRange(-1, 300), fdp.ConsumeRegularFloat()) for _ in range(n_chunks)
    ]
    data = fdp.ConsumeBytes(fdp.remaining_bytes())
    chunks = sorted(raw_chunks) if fdp.ConsumeBool() else raw_chunks
    if chunks and fdp.ConsumeBool():
        chunks[0] = (0, chunks[0][1])
    kw = {"role": role, "strict": strict, "max_adu": max_adu}
    got_c = _outcome(lambda: _events(C.parse_stream(data, chunks=chunks or None, **kw)))
    got_py = _outcome(lambda: _events(PY.parse_stream(data, chunks=chunks or None, **kw)))
    if got_c != got_py:
        raise AssertionError(f"parse_stream differs: C {got_c!r} / Python {got_py!r}")
    if got_c[0] == "ok":
        pos = 0
        for _kind, adu, offset, error, _s, _e in got_c[1]:  # type: ignore[union-attr]
            assert offset == pos, "events do not tile the input"
            assert error is not None or C.check_crc(adu), "a frame with a wrong CRC"
            pos += len(adu)
        assert pos == len(data)

    def framer(b: Any) -> object:
        f = b.Framer(role, strict=strict, max_adu=max(4, min(max_adu, 1024)))
        pos = 0
        for offset, t in chunks:
            end = max(pos, min(len(data), offset))
            f.receive_data(data[pos:end], t)
            if (deadline := f.timer()) is not None:
                f.handle_timer(deadline)
            pos = end
        f.receive_data(data[pos:], 1e6)
        f.handle_timer(2e6)
        return _events(f.events()), sorted(f.counters.items())

    got_c = _outcome(lambda: framer(C))
    got_py = _outcome(lambda: framer(PY))
    if got_c != got_py:
        raise AssertionError(f"Framer differs: C {got_c!r} / Python {got_py!r}")


def test_one_input(data: bytes) -> None:
    fdp = atheris.FuzzedDataProvider(data)
    if fdp.ConsumeBool():
        _pdu_layer(fdp)
    else:
        _stream(fdp)


def main() -> None:
    atheris.Setup(sys.argv, test_one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
