"""The gateway's own CPU per forwarded transaction, in this process (issue 12).

    python bench/investigations/profile_gateway.py [--bus instant|pty] [--transactions N]
        [--clients C] [--profile FILE] [--json]

A `pyrtu.gateway.Gateway` runs in this process's event loop; the clients are the
libmodbus TCP client's ``bench`` (tests/peers/libmodbus_client.c: N FC 03 reads of
10 registers, one in flight, every answer checked), each a process of its own, so
this process's CPU is the gateway's alone.

``--bus pty`` (the default): the bus is `pyrtu.drivers.aio.AsyncMaster` on a pseudo-terminal
pair (socat, ``t35=0``) with the pyrtu slave of tests/peers/pyrtu_slave.py (its own
process) on the other end: the whole path, TCP receive -> queue -> serial
transaction -> TCP send.  ``--bus instant``: a bus whose ``request`` returns the
answer at once (no I/O), which leaves the gateway's own code (listener, MBAP framer,
routes, fair queue, worker, answer) and nothing else.  ``--bus floor``: no gateway, a
bare asyncio Protocol answering each request in ``data_received`` (one read, one
write, one loop iteration per transaction): the floor of any asyncio server here.

Output: transactions, CPU seconds of this process (``time.process_time``) and CPU µs
per transaction; with ``--profile FILE`` a cProfile of the run (pstats file).
Instruction counts, robust on a loaded machine: run under callgrind twice and take
the difference (start-up cancels)::

    valgrind --tool=callgrind --callgrind-out-file=/tmp/cg.%p \\
        python bench/investigations/profile_gateway.py --bus instant --transactions 500
    (again with --transactions 2500; Ir difference / 2000 = instructions per transaction)

``bench/investigations/callgrind_gateway.sh`` does exactly that.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import cProfile
import json
import os
import resource
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1]
ROOT = BENCH.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

from peers import pattern  # noqa: E402
from peers.tools import PeerBinaries, build_peers, pyrtu_slave_process, socat_pair  # noqa: E402

from pyrtu.gateway import Gateway  # noqa: E402


class FloorServer(asyncio.Protocol):
    """``--bus floor``: no gateway at all; each ADU read is answered in ``data_received``
    with the answer of InstantBus (its transaction id copied): the least an asyncio
    server can spend per transaction (one read, one write, one loop iteration), the
    floor to judge the gateway's own cost against.  Assumes whole ADUs per read (the
    libmodbus client sends one request and waits)."""

    def __init__(self, bus: InstantBus) -> None:
        self.bus = bus
        self.transport: asyncio.Transport | None = None
        self.answers = 0

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        answer = self.bus.answers.get(data[7:])
        if answer is None:
            request = asyncio.get_running_loop().create_task(self.bus.request(1, data[7:]))
            request.add_done_callback(lambda t: self.data_received(data))
            return
        assert self.transport is not None
        header = data[:4] + (len(answer) + 1).to_bytes(2, "big") + data[6:7]
        self.transport.write(header + answer)
        self.answers += 1


class InstantBus:
    """A bus that answers FC 03 from the register pattern at once: no I/O, no wait."""

    def __init__(self) -> None:
        self.answers: dict[bytes, bytes] = {}

    async def request(self, slave: int, request: bytes) -> bytes | None:
        answer = self.answers.get(request)
        if answer is None:
            address = int.from_bytes(request[1:3], "big")
            count = int.from_bytes(request[3:5], "big")
            values = pattern.holdings(slave, address, count)
            answer = bytes((3, 2 * count)) + b"".join(v.to_bytes(2, "big") for v in values)
            self.answers[request] = answer
        return answer


@contextlib.asynccontextmanager
async def bus(kind: str) -> AsyncIterator[object]:
    if kind == "instant":
        yield InstantBus()
        return
    from pyrtu.drivers.aio import AsyncMaster

    with socat_pair() as (gw_side, dev_side), pyrtu_slave_process(dev_side, 1, t35=0):
        async with AsyncMaster(gw_side, 115200, "N", t35=0.0, timeout=0.5) as master:
            await master.read_holding_registers(1, 0, 1)
            yield master


def cpu_since(before: resource.struct_rusage) -> tuple[float, float]:
    """(user, system) CPU seconds of this process since ``before``."""
    now = resource.getrusage(resource.RUSAGE_SELF)
    return now.ru_utime - before.ru_utime, now.ru_stime - before.ru_stime


async def client(binaries: PeerBinaries, url: str, transactions: int) -> dict[str, object]:
    proc = await asyncio.create_subprocess_exec(
        str(binaries.client), url, "1", "--warmup", "20", "bench", str(transactions), "0",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, err = await proc.communicate()
    if proc.returncode != 0 or not out.strip():
        raise RuntimeError(f"libmodbus bench failed: {err.decode(errors='replace')}")
    report: dict[str, object] = json.loads(out.decode().splitlines()[-1])
    return report


async def floor(transactions: int, clients: int, binaries: PeerBinaries) -> dict[str, object]:
    bus = InstantBus()
    servers: list[FloorServer] = []

    def make() -> FloorServer:
        servers.append(FloorServer(bus))
        return servers[-1]

    server = await asyncio.get_running_loop().create_server(make, "127.0.0.1", 0)
    host, port = server.sockets[0].getsockname()[:2]
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    reports = await asyncio.gather(
        *(client(binaries, f"tcp:{host}:{port}", transactions) for _ in range(clients))
    )
    (user, system), wall = cpu_since(r0), time.monotonic() - t0
    cpu = user + system
    server.close()
    await server.wait_closed()
    done = sum(s.answers for s in servers)
    errors = sum(int(r["errors"]) + int(r["wrong"]) for r in reports)  # type: ignore[call-overload]
    return {
        "bus": "floor",
        "clients": clients,
        "transactions": done,
        "errors": errors,
        "wall_s": round(wall, 3),
        "tps": round(done / wall, 1),
        "cpu_s": round(cpu, 3),
        "cpu_us_per_tx": round(cpu / max(done, 1) * 1e6, 1),
        "user_us_per_tx": round(user / max(done, 1) * 1e6, 1),
    }


async def run(
    kind: str, transactions: int, clients: int, binaries: PeerBinaries
) -> dict[str, object]:
    if kind == "floor":
        return await floor(transactions, clients, binaries)
    async with bus(kind) as b:
        gw = Gateway([(b, range(1, 248))])  # type: ignore[list-item]
        await gw.start("127.0.0.1", 0)
        assert gw.address is not None
        url = f"tcp:{gw.address[0]}:{gw.address[1]}"
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
        reports = await asyncio.gather(
            *(client(binaries, url, transactions) for _ in range(clients))
        )
        (user, system), wall = cpu_since(r0), time.monotonic() - t0
        cpu = user + system
        stats = gw.stats()
        await gw.close()
    forwarded = int(stats["answers"])  # type: ignore[call-overload]
    errors = sum(int(r["errors"]) + int(r["wrong"]) for r in reports)  # type: ignore[call-overload]
    return {
        "bus": kind,
        "clients": clients,
        "transactions": forwarded,
        "errors": errors + int(stats["exceptions"]),  # type: ignore[call-overload]
        "wall_s": round(wall, 3),
        "tps": round(forwarded / wall, 1),
        "cpu_s": round(cpu, 3),
        "cpu_us_per_tx": round(cpu / max(forwarded, 1) * 1e6, 1),
        "user_us_per_tx": round(user / max(forwarded, 1) * 1e6, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--bus", choices=("pty", "instant", "floor"), default="pty")
    parser.add_argument("--transactions", type=int, default=3000, help="per client")
    parser.add_argument("--clients", type=int, default=1)
    parser.add_argument("--profile", type=Path, help="write a cProfile (pstats) of the run")
    parser.add_argument("--json", action="store_true", help="one JSON line")
    args = parser.parse_args()
    binaries = build_peers(Path(os.environ.get("PYRTU_PEERS", "/tmp/pyrtu-bench-peers")))
    profiler = cProfile.Profile() if args.profile else None
    if profiler:
        profiler.enable()
    result = asyncio.run(run(args.bus, args.transactions, args.clients, binaries))
    if profiler:
        profiler.disable()
        profiler.dump_stats(args.profile)
    print(json.dumps(result) if args.json else result, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
