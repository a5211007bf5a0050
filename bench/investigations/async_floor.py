"""The asyncio floor under `AsyncMaster`'s CPU per transaction (issue 18, target (a)).

    python bench/investigations/async_floor.py [--rounds N] [--bauds 9600 115200] [--wakes]

On bench_client.py's virtual bus and pyrtu slave, interleaved in each round, each in
a fresh interpreter: the libmodbus client (C), the sync `Master`, `AsyncMaster` on
`pyrtu.drivers.aio.run`, and FLOOR: the least an asyncio master can do on the same
loop for the same transaction (FC 03 x 10), written out by hand: one timer for t3.5
after the answer, the write, one timer for the answer's end (a reader for what is
still missing), the future the awaiting coroutine wakes on; no protocol, no framer,
no checks.  Three loop iterations per transaction (two timed wake-ups and the
task's wake-up): what `AsyncMaster` cannot go below on an asyncio loop.  Medians of
the rounds, and each master's ratio to libmodbus.

``--wakes`` adds the wake-ups alone (`WAKES`): programs that do nothing but wait out
one transaction period per transaction, with a thread's sleep, the event loop's
timer, or a sleep on a thread of its own that then wakes the loop (the shape of
`AsyncMaster`'s xfer thread): what one wake-up per transaction costs this
machine, before any I/O.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # bench/

import bench_client

ROOT = str(Path(__file__).resolve().parents[2])

#: the hand-written floor (see the module docstring); prints tx/s and CPU us per tx
FLOOR = r"""
import asyncio, os, sys, time
import serial
from pyrtu.core import _backend
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import run
path, n, baud = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
ser = serial.Serial(path, baud, timeout=0)  # (kept: its descriptor is read)
fd = ser.fd
req = _backend.active.add_crc(bytes.fromhex("07030000000a"))
line = LineConfig(baudrate=baud, parity="N")
t35, answer_time = line.t35_time, line.t35_time + 33 * line.char_time
async def main():
    loop = asyncio.get_running_loop()
    last = [time.monotonic()]
    async def one():
        fut, buf, reading = loop.create_future(), bytearray(), [False]
        def got():
            try:
                buf.extend(os.read(fd, 256))
            except BlockingIOError:
                pass
            if len(buf) >= 25:
                if reading[0]:
                    loop.remove_reader(fd)
                last[0] = time.monotonic()
                fut.set_result(bytes(buf))
            elif not reading[0]:
                reading[0] = True
                loop.add_reader(fd, got)
        def send():
            try:
                os.read(fd, 256)
            except BlockingIOError:
                pass
            os.write(fd, req)
            loop.call_at(time.monotonic() + answer_time, got)
        loop.call_at(last[0] + t35, send)
        return await fut
    for _ in range(5):
        await one()
    c0, t0 = time.process_time(), time.perf_counter()
    for _ in range(n):
        await one()
    print(n / (time.perf_counter() - t0), (time.process_time() - c0) / n * 1e6)
run(main())
"""


#: the wake-up alone: a program that does nothing per transaction but wait out its
#: period (t3.5 + 8 characters + t3.5 + 25 characters at the bus's rate) once; the
#: least CPU a master that sleeps once per transaction can use on this machine.
#: ``{SETUP}``, ``{WAIT}``: statements (``period`` in seconds); ``{RUN}``: how main runs
_WAKE = r"""
import asyncio, sys, threading, time
from pyrtu.core.line import LineConfig
from pyrtu.drivers.aio import run
path, n, baud = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
line = LineConfig(baudrate=baud, parity="N")
period = 2 * line.t35_time + 33 * line.char_time
async def main():
    loop = asyncio.get_running_loop()
    {SETUP}
    for _ in range(5):
        {WAIT}
    c0, t0 = time.process_time(), time.perf_counter()
    for _ in range(n):
        {WAIT}
    print(n / (time.perf_counter() - t0), (time.process_time() - c0) / n * 1e6)
{RUN}
"""
#: the wake-ups: a thread's sleep; the event loop's timer (asyncio.sleep) on
#: pyrtu.drivers.aio.run; a sleep on a thread of its own whose end wakes the loop
#: (call_soon_threadsafe), as AsyncMaster's xfer thread does
WAKES = {
    "sleep": _WAKE.replace("{SETUP}", "pass")
    .replace("{WAIT}", "time.sleep(period)")
    .replace("{RUN}", "asyncio.run(main())"),
    "asyncio sleep": _WAKE.replace("{SETUP}", "pass")
    .replace("{WAIT}", "await asyncio.sleep(period)")
    .replace("{RUN}", "run(main())"),
    "thread handoff": _WAKE.replace(
        "{SETUP}",
        "go, box = threading.Event(), []\n"
        "    def worker():\n"
        "        while True:\n"
        "            go.wait(); go.clear(); time.sleep(period)\n"
        "            loop.call_soon_threadsafe(box.pop().set_result, None)\n"
        "    threading.Thread(target=worker, daemon=True).start()",
    )
    .replace("{WAIT}", "f = loop.create_future(); box.append(f); go.set(); await f")
    .replace("{RUN}", "run(main())"),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--bauds", type=int, nargs="+", default=[9600, 115200])
    ap.add_argument(
        "--wakes",
        action="store_true",
        help="add the wake-ups alone (WAKES): one sleep per transaction period, nothing else",
    )
    args = ap.parse_args()
    programs = {
        "floor": FLOOR,
        "Master": bench_client._BASELINE,
        "AsyncMaster": bench_client._BASELINE_ASYNC,
    }
    if args.wakes:
        programs.update(WAKES)

    def one_round(i: int, path: str, baud: int, n: int) -> Iterator[tuple[str, float]]:
        for name, program in programs.items():
            yield name, bench_client.baseline_master(ROOT, path, baud, n, program)["cpu_us"]

    print("| baud | program | µs/tx | / libmodbus |")
    print("|---:|---|---:|---:|")
    for baud, med in bench_client.cpu_rounds(args.bauds, args.rounds, one_round):
        for name in [*programs, "libmodbus"]:
            print(f"| {baud} | {name} | {med[name]:.0f} | {med[name] / med['libmodbus']:.2f}x |")


if __name__ == "__main__":
    main()
