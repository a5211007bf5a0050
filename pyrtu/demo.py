"""``pyrtu demo``: the README's main job.

Builds a short capture of RTU traffic on a shared bus (requests, responses of two
slaves, an exception, a vendor code, noise and a frame cut by a USB adapter's
latency), decodes it with the monitor framer of the active backend, and prints
every frame and discard event.
"""

from __future__ import annotations

import argparse

import pyrtu

from .frames import FrameKind

FUNCTION_NAMES = {
    1: "read coils",
    2: "read discrete inputs",
    3: "read holding registers",
    4: "read input registers",
    5: "write single coil",
    6: "write single register",
    7: "read exception status",
    8: "diagnostics",
    11: "get comm event counter",
    12: "get comm event log",
    15: "write multiple coils",
    16: "write multiple registers",
    17: "report server id",
    20: "read file record",
    21: "write file record",
    22: "mask write register",
    23: "read/write registers",
    24: "read FIFO queue",
    43: "encapsulated interface (device identification)",
    100: "Bonfiglioli: read 32-bit parameter",
    101: "Bonfiglioli: write 32-bit parameter",
}


def function_name(code: int) -> str:
    base = FUNCTION_NAMES.get(code & 0x7F, f"function {code & 0x7F}")
    return f"exception of {base}" if code & 0x80 else base


def demo_capture() -> tuple[bytes, list[tuple[int, float]]]:
    """(data, chunks) of a small bus capture at 19200 baud 8E1."""
    add = pyrtu.add_crc
    t = 10.0
    parts: list[tuple[bytes, float]] = []

    def put(data: bytes, gap: float) -> None:
        nonlocal t
        t += gap + len(data) * 11 / 19200
        parts.append((data, t))

    put(add(bytes.fromhex("010300000002")), 0.0)  # read P0000..P0001 of slave 1
    put(add(bytes.fromhex("010304000a0014")), 0.004)
    put(add(bytes.fromhex("02060064012c")), 0.010)  # write 300 to register 100 of slave 2
    put(add(bytes.fromhex("02060064012c")), 0.004)
    put(b"\x00\xff\x13", 0.010)  # noise on the line
    put(add(bytes.fromhex("0103ffff0001")), 0.010)  # an address that does not exist
    put(add(bytes.fromhex("018302")), 0.004)
    put(add(bytes.fromhex("026401e1")), 0.010)  # Bonfiglioli FC 100, parameter 481
    put(add(bytes.fromhex("02640000c350")), 0.004)
    frame = add(bytes.fromhex("011000000002040001000a"))
    put(frame[:6], 0.010)  # a USB adapter delivers half a frame ...
    put(frame[6:], 0.016)  # ... and the rest 16 ms later
    put(add(bytes.fromhex("011000000002")), 0.004)
    data = b"".join(p for p, _ in parts)
    chunks = []
    offset = 0
    for p, at in parts:
        chunks.append((offset, at))
        offset += len(p)
    return data, chunks


def run_core_demo() -> int:
    data, chunks = demo_capture()
    frames = pyrtu.parse_stream(data, "monitor", chunks=chunks, rules=pyrtu.BONFIGLIOLI)
    paths = ", ".join(pyrtu.crc16_paths())
    print(f"pyrtu {pyrtu.__version__}, backend: {pyrtu.BACKEND}, CRC paths: {paths}")
    print(f"decoding a {len(data)}-byte capture of a 19200 baud bus (monitor role):")
    t0 = frames[0].start if frames and frames[0].start is not None else 0.0
    for f in frames:
        at = f"{(f.start or t0) - t0:8.4f}s"
        if f.error:
            print(f"  {at}  DISCARD   {len(f.adu)} bytes ({f.error}): {f.adu.hex(' ')}")
            continue
        detail = f"code {f.exception_code}" if f.kind is FrameKind.EXCEPTION else f.pdu[1:].hex(" ")
        name = function_name(f.function)
        print(f"  {at}  {f.kind.name:<9} slave {f.address:3d}  {name:<40} {detail}")
    counts = frames.counters
    discarded = sum(v for k, v in counts.items() if k.startswith("discarded_"))
    print(
        f"{counts['request']} requests, {counts['response']} responses, "
        f"{counts['exception']} exceptions, {discarded} bytes discarded"
    )
    return 0


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--core", action="store_true", help="only the core demonstration (decode a capture)"
    )


def run(args: argparse.Namespace) -> int:
    return run_core_demo()
