"""Modbus/TCP Security's cost on the client (issue 31's targets), in one run against
one pyrtu TLS listener (a `TcpServer` with a plain and a TLS listener, in a process
of its own so that only the client's CPU is counted here).

    python bench/bench_mbaps.py [--transactions 2000] [--rounds 5] [--connects 200] [--json FILE]

Both paths of the sync client's TLS are measured: the C core over OpenSSL
(csrc/rtu_tls_io.c: the handshake and each transaction in C, the GIL released) and
the Python ssl fallback (``backend="python"``; what runs where the C core was built
without OpenSSL).  The targets are the C path's.

1. CPU per transaction of the sync `pyrtu.Master` on an established connection:
   ``mbaps://`` (C TLS, and the fallback) against plain ``tcp://`` (target: at most
   1.5x), reads of 10 holding registers, ``--rounds`` interleaved rounds of
   ``--transactions`` each, the median round.  To say where a difference comes
   from, the same on ``tcp://`` with the pure-Python backend (the fallback's
   transaction is Python over the ssl module), and the ssl module's own cost of one
   request and answer of the same sizes (``sendall`` + ``recv`` on an established
   TLS connection to a TLS echo, no Modbus).
2. CPU of the client per reconnect (TCP connect and TLS handshake, measured around
   `pyrtu.tcp.TcpClient.reconnect`, what a master does when its connection broke),
   on each path: a reconnect resuming the TLS session against one with a full
   handshake (target: at most 0.3x), the median of
   ``--connects`` each, interleaved; on TLS 1.3 (what pyrtu negotiates) and TLS 1.2
   (the minimum), since TLS 1.3's resumption still runs an ECDHE exchange
   (psk_dhe_ke) while TLS 1.2's abbreviated handshake runs none.

3. The reference for 2.: OpenSSL's own client, ``openssl s_time`` (``-new`` against
   ``-reuse``, each TLS version, ``--stime-rounds`` interleaved rounds of
   ``--stime-seconds``) against ``openssl s_server -www`` with the same certificates
   (client certificate required).  s_time counts its user CPU only (``connections/user
   sec``), so our client's user CPU per connect is given beside it (from
   `resource.getrusage`, the mean over the ``--connects``); and s_time's user +
   system CPU (the target's measure), from `resource.getrusage` of the children
   over each round: what OpenSSL itself reaches on this machine is the floor of any
   client built on it.

Certificates: made here with tests/tls_certs.py (P-256 ECDSA, as the tests').
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import multiprocessing
import platform
import re
import resource
import shutil
import socket
import ssl
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from tls_certs import Pki, make_pki  # noqa: E402

from pyrtu import DataStore, Master, PortError  # noqa: E402
from pyrtu.core import _backend  # noqa: E402
from pyrtu.core import _tls as ctls  # noqa: E402
from pyrtu.security.tls import TlsListen, client_context, server_context  # noqa: E402
from pyrtu.tcp import TcpClient  # noqa: E402
from pyrtu.tcp.server import TcpServer  # noqa: E402
from pyrtu.tcp.tls import forget_sessions  # noqa: E402

#: the two paths of an mbaps:// client: the C core over OpenSSL (csrc/rtu_tls_io.c),
#: and the Python ssl module (the fallback: what ``backend="python"`` runs, and every
#: backend where the C core was built without OpenSSL), named by the backend that
#: picks them (and the client's ``tls_path`` says)
PATHS = ("c", "python")
PATH_NAMES = {"c": "C TLS", "python": "Python ssl fallback"}
C_TLS = "c" in _backend.available_backends() and ctls.available(_backend.backend("c"))
TARGET_TRANSACTION = 1.5
TARGET_RESUME = 0.3
#: a read of 10 holding registers: request ADU 12 bytes, answer ADU 29 bytes
REQUEST = bytes.fromhex("00010000000601030000000a")
ANSWER_BYTES = 29


def serve(folder: str, pipe: Connection) -> None:
    """The listener's process: a `TcpServer` (plain and TLS) and a TLS echo of one
    answer's size per request; sends the three ports, runs until the pipe closes."""
    pki = _pki_of(Path(folder))

    async def main() -> None:
        store = DataStore()
        store.holding_registers.add_range(0, list(range(100)))
        server = TcpServer.for_store(1, store)
        context = server_context(pki.server.cert, pki.server.key, pki.ca.path)
        await server.start("127.0.0.1", 0, tls=TlsListen("127.0.0.1", 0, context))

        async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            try:
                while await reader.readexactly(len(REQUEST)):
                    writer.write(bytes(ANSWER_BYTES))
            except (asyncio.IncompleteReadError, ConnectionError, ssl.SSLError):
                pass
            writer.close()

        echo_server = await asyncio.start_server(echo, "127.0.0.1", 0, ssl=context)
        plain_echo = await asyncio.start_server(echo, "127.0.0.1", 0)
        assert server.address is not None and server.tls_address is not None
        ports = (server.address[1], server.tls_address[1], echo_server.sockets[0].getsockname()[1],
                 plain_echo.sockets[0].getsockname()[1])  # fmt: skip
        pipe.send(ports)
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, _wait_closed, pipe)
        await server.close()
        echo_server.close()
        plain_echo.close()

    asyncio.run(main())


def _wait_closed(pipe: Connection) -> None:
    try:
        pipe.recv()
    except EOFError:
        pass


_PKI: dict[Path, Pki] = {}


def _pki_of(folder: Path) -> Pki:
    """The certificates in ``folder`` (made once, by the parent, before the fork)."""
    if folder not in _PKI:
        _PKI[folder] = make_pki(folder)
    return _PKI[folder]


def cpu_per_call(call: Callable[[], object], n: int) -> float:
    """Seconds of this process's CPU per ``call()``, over ``n`` calls."""
    start = time.process_time()
    for _ in range(n):
        call()
    return (time.process_time() - start) / n


def transactions(
    args: argparse.Namespace, pki: Pki, ports: tuple[int, int, int, int]
) -> dict[str, Any]:
    plain, tls_port, echo_port, plain_echo_port = ports
    context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
    masters = {
        "tcp (C core)": Master(f"tcp://127.0.0.1:{plain}", timeout=5.0),
        "tcp (Python backend)": Master(f"tcp://127.0.0.1:{plain}", timeout=5.0, backend="python"),
        "mbaps (C TLS)": Master(f"mbaps://localhost:{tls_port}", tls=context, timeout=5.0),
        "mbaps (Python ssl fallback)": Master(
            f"mbaps://localhost:{tls_port}", tls=context, timeout=5.0, backend="python"
        ),
    }
    raw = context.wrap_socket(
        socket.create_connection(("127.0.0.1", echo_port)), server_hostname="localhost"
    )
    raw.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    bare = socket.create_connection(("127.0.0.1", plain_echo_port))
    bare.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def echo(sock: socket.socket) -> Callable[[], None]:
        def once() -> None:
            sock.sendall(REQUEST)
            got = 0
            while got < ANSWER_BYTES:
                got += len(sock.recv(65536))

        return once

    calls: dict[str, Callable[[], object]] = {
        name: (lambda m=m: m.read_holding_registers(1, 0, 10)) for name, m in masters.items()
    }
    calls["ssl sendall+recv alone"] = echo(raw)
    calls["socket sendall+recv alone"] = echo(bare)
    for name, m in masters.items():
        assert m.read_holding_registers(1, 0, 10) == list(range(10)), name
    rounds: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(args.rounds):
        for name, call in calls.items():
            cpu_per_call(call, args.transactions // 10)  # warm
            rounds[name].append(cpu_per_call(call, args.transactions))
    for m in masters.values():
        m.close()
    raw.close()
    bare.close()
    us = {name: statistics.median(v) * 1e6 for name, v in rounds.items()}
    ratio = us["mbaps (C TLS)"] / us["tcp (C core)"]
    return {
        "us_per_transaction": us,
        "rounds_us": {name: [x * 1e6 for x in v] for name, v in rounds.items()},
        "ratio": ratio,
        "ratio_fallback": us["mbaps (Python ssl fallback)"] / us["tcp (C core)"],
        "ratio_python_backend": us["mbaps (Python ssl fallback)"] / us["tcp (Python backend)"],
        "c_tls": C_TLS,
        "ok": ratio <= TARGET_TRANSACTION,
    }


def _user_cpu() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_utime


def connect_once(
    client: TcpClient, failures: list[str], backend: str, user: list[float], forget: bool
) -> tuple[float, bool]:
    """Client CPU of one reconnect of ``client`` (TCP connect and TLS handshake: what
    a master does when its connection broke; the old connection closed first,
    outside the measure), and whether it resumed the session; then one transaction
    (TLS 1.3 sends its session tickets after the handshake).  A reset under load
    is counted and tried again.  ``user``: the connect's user CPU alone is appended
    (s_time's measure); ``forget``: the sessions kept are forgotten after the close
    (a full handshake)."""
    client.close()
    if forget:
        assert client._tls is not None
        forget_sessions(client._tls)
    for attempt in range(3):
        start, start_user = time.process_time(), _user_cpu()
        try:
            client.reconnect()
        except PortError as exc:
            failures.append(str(exc))
            if attempt == 2:
                raise
            continue
        break
    cpu = time.process_time() - start
    user.append(_user_cpu() - start_user)
    client.request(1, REQUEST[7:])
    assert client.tls_path == backend, (client.tls_path, backend)
    return cpu, client.session_reused


def connects(args: argparse.Namespace, pki: Pki, plain: int, tls_port: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    url = f"mbaps://localhost:{tls_port}"
    for version, backend in [(v, b) for v in ("TLSv1.3", "TLSv1.2") for b in PATHS]:
        if backend == "c" and not C_TLS:
            continue
        context = client_context(pki.operator.cert, pki.operator.key, pki.ca.path)
        context.maximum_version = ssl.TLSVersion[version.replace(".", "_")]
        full: list[float] = []
        resumed: list[float] = []
        full_user: list[float] = []
        resumed_user: list[float] = []
        reused = 0
        failures: list[str] = []
        client = TcpClient(url, timeout=5.0, tls=context, backend=backend)
        client.request(1, REQUEST[7:])  # a first session to resume
        for _ in range(args.connects):
            # the sessions forgotten: a full handshake
            cpu, again = connect_once(client, failures, backend, full_user, True)
            assert not again
            full.append(cpu)
            # the session of the one before: resumed
            cpu, again = connect_once(client, failures, backend, resumed_user, False)
            reused += again
            resumed.append(cpu)
        client.close()
        # the floors under both: the TCP connect (a reconnect of pyrtu's client on
        # tcp://) alone, and OpenSSL's per-connection setup (SSL_new from the
        # context: no handshake)
        tcp_floor: list[float] = []
        setup: list[float] = []
        plain_client = TcpClient(f"tcp://127.0.0.1:{plain}", timeout=5.0)
        for _ in range(args.connects):
            plain_client.close()
            start = time.process_time()
            plain_client.reconnect()
            tcp_floor.append(time.process_time() - start)
        plain_client.close()
        for _ in range(args.connects):
            sock = socket.create_connection(("127.0.0.1", tls_port))
            start = time.process_time()
            wrapped = context.wrap_socket(
                sock, server_hostname="localhost", do_handshake_on_connect=False
            )
            setup.append(time.process_time() - start)
            wrapped.close()
        ratio = statistics.median(resumed) / statistics.median(full)
        floor = statistics.median(tcp_floor) + statistics.median(setup)
        out[f"{version} ({PATH_NAMES[backend]})"] = {
            "full_us": statistics.median(full) * 1e6,
            "resumed_us": statistics.median(resumed) * 1e6,
            "tcp_connect_us": statistics.median(tcp_floor) * 1e6,
            "ssl_setup_us": statistics.median(setup) * 1e6,
            "handshake_ratio": (statistics.median(resumed) - floor)
            / (statistics.median(full) - floor),
            "resumed_share": reused / args.connects,
            # user CPU alone (getrusage: sampled, so the mean over all, not a median)
            "full_user_us": statistics.fmean(full_user) * 1e6,
            "resumed_user_us": statistics.fmean(resumed_user) * 1e6,
            "user_ratio": statistics.fmean(resumed_user) / statistics.fmean(full_user),
            "failed_connects": failures,
            "ratio": ratio,
            "ok": ratio <= TARGET_RESUME and reused == args.connects,
        }
    return out


_S_TIME = re.compile(r"(\d+) connections in [\d.]+s; ([\d.]+) connections/user sec")


def openssl_reference(args: argparse.Namespace, pki: Pki) -> dict[str, Any] | None:
    """OpenSSL's own client (``openssl s_time``) connecting anew and resuming, against
    ``openssl s_server -www`` with the same certificates: user CPU per connect (s_time's
    measure) on each TLS version, the median of ``--stime-rounds`` interleaved rounds.
    None where the openssl binary is missing."""
    openssl = shutil.which("openssl")
    if openssl is None:
        return None
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    files = ["-CAfile", str(pki.ca.path)]
    server = subprocess.Popen(
        [openssl, "s_server", "-quiet", "-www", "-accept", f"127.0.0.1:{port}", "-Verify", "1",
         "-cert", str(pki.server.cert), "-key", str(pki.server.key), *files],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 10.0
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError("openssl s_server did not start") from None
                time.sleep(0.05)
        out: dict[str, Any] = {}
        for version, flag in (("TLSv1.3", "-tls1_3"), ("TLSv1.2", "-tls1_2")):
            us: dict[str, list[float]] = {"new": [], "reuse": []}
            total: dict[str, list[float]] = {"new": [], "reuse": []}
            for _ in range(args.stime_rounds):
                for mode in us:
                    before = resource.getrusage(resource.RUSAGE_CHILDREN)
                    run = subprocess.run(
                        [openssl, "s_time", "-connect", f"localhost:{port}", f"-{mode}",
                         "-time", f"{args.stime_seconds:g}", "-cert", str(pki.operator.cert),
                         "-key", str(pki.operator.key), *files, flag, "-www", "/"],
                        capture_output=True, text=True, timeout=args.stime_seconds + 60,
                    )  # fmt: skip
                    after = resource.getrusage(resource.RUSAGE_CHILDREN)
                    found = _S_TIME.search(run.stdout)
                    if found is None:
                        raise RuntimeError(f"openssl s_time -{mode}: {run.stdout[-500:]}")
                    us[mode].append(1e6 / float(found.group(2)))
                    # its user + system CPU, the target's measure (the process's start
                    # and end included: a few ms over thousands of connects)
                    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
                    total[mode].append(cpu / int(found.group(1)) * 1e6)
            new, reuse = statistics.median(us["new"]), statistics.median(us["reuse"])
            new_cpu, reuse_cpu = statistics.median(total["new"]), statistics.median(total["reuse"])
            out[version] = {"new_user_us": new, "reuse_user_us": reuse, "ratio": reuse / new,
                            "new_cpu_us": new_cpu, "reuse_cpu_us": reuse_cpu,
                            "cpu_ratio": reuse_cpu / new_cpu,
                            "rounds_us": us, "rounds_cpu_us": total}  # fmt: skip
        return out
    finally:
        server.terminate()
        server.wait(10)


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--transactions", type=int, default=2000, help="per round and client")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--connects", type=int, default=200, help="of each kind, per TLS version")
    ap.add_argument("--stime-rounds", type=int, default=3, help="of openssl s_time, each kind")
    ap.add_argument("--stime-seconds", type=float, default=3.0, help="per s_time round")
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as folder:
        pki = _pki_of(Path(folder))
        parent, child = multiprocessing.get_context("fork").Pipe()
        proc = multiprocessing.get_context("fork").Process(target=serve, args=(folder, child))
        proc.start()
        try:
            ports: tuple[int, int, int, int] = parent.recv()
            trans = transactions(args, pki, ports)
            conn = connects(args, pki, ports[0], ports[1])
            reference = openssl_reference(args, pki)
        finally:
            parent.close()
            proc.join(30)
            if proc.is_alive():
                proc.terminate()
    lines = [f"CPU per transaction, sync Master, read of 10 registers (median of {args.rounds} "
             f"rounds of {args.transactions}):"]  # fmt: skip
    for name, us in trans["us_per_transaction"].items():
        lines.append(f"  {name:28} {us:8.1f} us")
    lines.append(
        f"  mbaps (C TLS) / tcp (C core): {trans['ratio']:.2f}x (target <= {TARGET_TRANSACTION}x: "
        f"{'met' if trans['ok'] else 'MISSED'}); the fallback / tcp (C core): "
        f"{trans['ratio_fallback']:.2f}x, / tcp (Python backend): "
        f"{trans['ratio_python_backend']:.2f}x"
        + ("" if C_TLS else " (C TLS not built: both mbaps rows are the fallback)")
    )
    lines.append(f"Client CPU per reconnect (median of {args.connects} each):")
    for version, r in conn.items():
        lines.append(
            f"  {version}: full handshake {r['full_us']:.0f} us, resumed {r['resumed_us']:.0f} us"
            f" ({r['resumed_share']:.0%} resumed): {r['ratio']:.2f}x (target <= {TARGET_RESUME}x:"
            f" {'met' if r['ok'] else 'MISSED'})"
        )
        lines.append(
            "    under both: TCP connect (a reconnect of pyrtu's TcpClient on tcp://) "
            f"{r['tcp_connect_us']:.0f} us,"
            f" SSL object setup {r['ssl_setup_us']:.0f} us; the handshakes alone: "
            f"{r['handshake_ratio']:.2f}x; user CPU alone: full {r['full_user_us']:.0f} us, "
            f"resumed {r['resumed_user_us']:.0f} us: {r['user_ratio']:.2f}x"
        )
    if reference is None:
        lines.append("openssl s_time: no openssl binary here")
    for version, r in (reference or {}).items():
        lines.append(
            f"  openssl s_time, {version} (user CPU): new {r['new_user_us']:.0f} us, "
            f"reuse {r['reuse_user_us']:.0f} us: {r['ratio']:.2f}x; user + system: new "
            f"{r['new_cpu_us']:.0f} us, reuse {r['reuse_cpu_us']:.0f} us: {r['cpu_ratio']:.2f}x"
        )
    print("\n".join(lines))
    if args.json:
        doc = {
            "transactions": trans,
            "connects": conn,
            "openssl_s_time": reference,
            "settings": {
                "transactions": args.transactions,
                "rounds": args.rounds,
                "connects": args.connects,
                "stime_rounds": args.stime_rounds,
                "stime_seconds": args.stime_seconds,
            },
            "openssl": ssl.OPENSSL_VERSION,
            "python": platform.python_version(),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "seconds": time.monotonic() - started,
        }
        args.json.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
