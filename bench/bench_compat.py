"""Drop-in figures of issue 20: stock pymodbus/minimalmodbus/umodbus/modbus_tk against
the same libraries with pyrtu.compat installed, measured in one run.

    .venv/bin/python bench/bench_compat.py [--requests 100] [--json out.json]

Measurements, not tests (nothing is asserted): the numbers go to bench/RESULTS.md.

* shared bus: a pymodbus ModbusSerialServer (device 1) and a pyrtu Slave (device 2) on
  one virtual bus at 19200 baud, a pymodbus AsyncModbusSerialClient alternating between
  them (timeout 0.25 s, no retries): clean, with 16 ms USB-style batching on the pymodbus
  server's drop, and with seeded line noise (bit flips);
* damaged answers to a pymodbus client (sync and asyncio): a leading 0x00, a stale echo
  of the request, a bad frame followed by a good retransmission;
* 10,000 FC 03 answers back to back in one buffer through ``handleFrame``;
* per-frame decode inside pymodbus (``FramerRTU.decode`` and ``handleFrame``, 25- and
  255-byte FC 03 answers) and the CRC functions inside minimalmodbus, umodbus and
  modbus_tk (8 and 256 bytes): medians of 21 timeit repeats, stock and installed
  interleaved; "installed via cffi" is the same replacement through the cffi core (as
  before pyrtu.core._crcfast), measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import platform
import random
import statistics
import sys
import timeit
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "tests" / "compat")]
sys.path.insert(0, str(ROOT))

import pyrtu  # noqa: E402
from pyrtu import add_crc  # noqa: E402


def medians_us(
    fns: dict[str, Callable[[], object]], number: int, repeat: int = 21
) -> dict[str, float]:
    """Median microseconds per call of each function, the repeats interleaved (one
    repeat of each in turn) so that a change of load on the machine hits all alike."""
    times: dict[str, list[float]] = {name: [] for name in fns}
    timers = {name: timeit.Timer(fn) for name, fn in fns.items()}
    for _ in range(repeat):
        for name, timer in timers.items():
            times[name].append(timer.timeit(number) / number * 1e6)
    return {name: statistics.median(t) for name, t in times.items()}


def bus_figures(n: int) -> dict[str, Any]:
    from test_compat_pymodbus_bus import DAMAGES, damaged_answer_run, shared_bus_run

    out: dict[str, Any] = {}
    for name, kw in (
        ("clean", {}),
        ("batch 16 ms", {"batch_s": 0.016, "timeout": 0.3}),
        ("noise 2e-4", {"bit_flip_rate": 2e-4, "seed": 7}),
    ):
        for installed in (False, True):
            run = shared_bus_run(n, installed=installed, **kw)
            key = f"shared bus, {name}, {'installed' if installed else 'stock'}"
            out[key] = {
                "answered": run.total,
                "device 1": run.answered[1],
                "device 2": run.answered[2],
                "failed": sum(run.failed.values()),
                "wrong": run.wrong,
                "seconds": round(run.seconds, 2),
            }
            print(key, out[key], flush=True)
    for damage in sorted(DAMAGES):
        for sync in (True, False):
            for installed in (False, True):
                got = damaged_answer_run(damage, 10, installed=installed, sync=sync)
                key = (
                    f"client {'sync' if sync else 'asyncio'}, {damage}, "
                    f"{'installed' if installed else 'stock'}"
                )
                out[key] = f"{got}/10"
                print(key, out[key], flush=True)
    return out


def decode_figures() -> dict[str, Any]:
    from pymodbus.framer import FramerRTU
    from pymodbus.pdu import DecodePDU
    from pymodbus.pdu.register_message import ReadHoldingRegistersRequest

    from pyrtu.compat.pymodbus import PyrtuFramerRTU

    out: dict[str, Any] = {}
    for size in (25, 255):
        count = (size - 5) // 2
        adu = add_crc(bytes((1, 3, 2 * count)) + random.Random(size).randbytes(2 * count))
        fns: dict[str, Callable[[], object]] = {}
        for name, cls in (("stock", FramerRTU), ("installed", PyrtuFramerRTU)):
            f = cls(DecodePDU(False))
            f.buildFrame(ReadHoldingRegistersRequest(address=0, count=count, dev_id=1))
            assert f.handleFrame(adu, 1, 0)[1] is not None
            fns[f"decode {name} us"] = lambda f=f, adu=adu: f.decode(adu)
            fns[f"handleFrame {name} us"] = lambda f=f, adu=adu: f.handleFrame(adu, 1, 0)
        row = {k: round(v, 2) for k, v in medians_us(fns, 2000).items()}
        row["decode ratio"] = round(row["decode stock us"] / row["decode installed us"], 1)
        row["handleFrame ratio"] = round(
            row["handleFrame stock us"] / row["handleFrame installed us"], 1
        )
        out[f"pymodbus {size} B"] = row
        print(f"pymodbus {size} B", row, flush=True)
    # 10,000 FC 03 answers back to back in one buffer, handleFrame called until it
    # uses nothing more (what pymodbus's transport does with what it keeps)
    stream = b"".join(
        add_crc(bytes((1, 3, 4)) + i.to_bytes(2, "big") + b"\x00\x07") for i in range(10_000)
    )
    for name, cls in (("stock", FramerRTU), ("installed", PyrtuFramerRTU)):
        f = cls(DecodePDU(False))
        f.buildFrame(ReadHoldingRegistersRequest(address=0, count=2, dev_id=1))
        buf, got = stream, 0
        while buf:
            used, pdu = f.handleFrame(buf, 1, 0)
            if not used:
                break
            got += pdu is not None
            buf = buf[used:]
        out[f"concatenated answers, {name}"] = f"{got}/10000"
        print(f"concatenated answers, {name}: {got}/10000", flush=True)
    return out


def crc_figures() -> dict[str, Any]:
    """Stock, installed (pyrtu.core._crcfast's builtins when built) and installed through
    cffi (the shapes of pyrtu.core.crcshapes over the cffi core, as before _crcfast)."""
    import minimalmodbus
    import modbus_tk.utils
    import umodbus.client.serial.redundancy_check as rc

    import pyrtu.compat.minimalmodbus as c_mm
    import pyrtu.compat.modbus_tk as c_tk
    import pyrtu.compat.umodbus as c_um
    from pyrtu.core import crcshapes as _crcshapes

    def mm_cffi(inputbytes: bytes) -> bytes:  # c_mm._calculate_crc over cffi
        if not isinstance(inputbytes, bytes):
            raise TypeError(f"The CRC input bytes should be bytes. Given: {inputbytes!r}")
        return _crcshapes._crc16_bytes(inputbytes)

    cases = {
        "minimalmodbus _calculate_crc": (
            minimalmodbus._calculate_crc,
            c_mm._calculate_crc,
            mm_cffi,
        ),
        "umodbus get_crc": (rc.get_crc, c_um.get_crc, _crcshapes._crc16_bytes),
        "modbus_tk calculate_crc": (
            modbus_tk.utils.calculate_crc,
            c_tk.calculate_crc,
            _crcshapes._crc16_swapped,
        ),
    }
    out: dict[str, Any] = {"crc builtins": _crcshapes._fast is not None}
    for name, (stock, ours, cffi) in cases.items():
        for size in (8, 256):
            data = random.Random(size).randbytes(size)
            assert stock(data) == ours(data) == cffi(data)
            m = medians_us(
                {
                    "stock": lambda stock=stock, data=data: stock(data),
                    "ours": lambda ours=ours, data=data: ours(data),
                    "cffi": lambda cffi=cffi, data=data: cffi(data),
                },
                2000,
            )
            s, o, c = m["stock"], m["ours"], m["cffi"]
            out[f"{name} {size} B"] = {
                "stock us": round(s, 3),
                "installed us": round(o, 3),
                "ratio": round(s / o, 1),
                "installed via cffi us": round(c, 3),
                "ratio via cffi": round(s / c, 1),
            }
            print(f"{name} {size} B", out[f"{name} {size} B"], flush=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=100)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--no-bus", action="store_true", help="timings only")
    parser.add_argument("--crc-only", action="store_true", help="the CRC timings only")
    args = parser.parse_args()
    versions = {
        d: metadata.version(d) for d in ("pymodbus", "minimalmodbus", "umodbus", "modbus_tk")
    }
    result: dict[str, Any] = {
        "versions": versions,
        "pyrtu backend": pyrtu.BACKEND,
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    print(result, flush=True)
    if not args.crc_only:
        result["decode"] = decode_figures()
    result["crc"] = crc_figures()
    if not (args.no_bus or args.crc_only):
        result["bus"] = bus_figures(args.requests)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
