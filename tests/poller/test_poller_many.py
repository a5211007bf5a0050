"""Many ``tcp://`` devices in one poller (issue 30, item 3): the ``[connect]`` table,
connects bounded in the poller and per host, a staggered start, reconnect jitter,
the event loop for more descriptors than ``select()`` takes, and the short version
of bench/bench_many_devices.py: devices served by one ``pyrtu simulate --tcp
FIRST-LAST`` process, one of them silent, one refusing, one whose connect never
completes, and the others keeping their period."""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import random
import resource
import selectors
import socket
import statistics
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from cli_helpers import Background, free_port_range
from waiting import wait_for

from pyrtu.drivers.aio import SELECT_LIMIT, new_event_loop
from pyrtu.drivers.aio import run as aio_run
from pyrtu.poller import Bus, ConfigError, Point, Poller, PortState, make_config, parse_config
from pyrtu.poller.connect import ConnectLimits
from pyrtu.poller.driver import wake_tick
from pyrtu.poller.events import Tracker, Update
from pyrtu.protocol.datastore import DataStore
from pyrtu.tcp.server import TcpServer

#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 60.0


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


# ---------------------------------------------------------------- the [connect] table

BUS = '[[bus]]\nname = "t"\nport = "tcp://127.0.0.1:1502"\n\n'
POINT = '[[point]]\nname = "x"\nbus = "t"\nslave = 1\ntable = "holding"\naddress = 0\n'


def test_connect_defaults_without_a_table() -> None:
    cfg = parse_config(BUS + POINT, "p.toml")
    assert cfg.connect == ConnectLimits(64, 8, 1000.0, 0.5, 0.025)


def test_connect_table_read() -> None:
    text = (
        "[connect]\nmax_connecting = 1\nmax_connecting_per_host = 1\n"
        "start_rate = 0.5\njitter = 0.0\nlateness = 0.5\n\n" + BUS + POINT
    )
    cfg = parse_config(text, "p.toml")
    # the boundaries: one connect at a time, no jitter, the most lateness
    assert cfg.connect == ConnectLimits(1, 1, 0.5, 0.0, 0.5)
    assert cfg.connect.start_offset(3) == 6.0  # the 4th network bus: 3 / 0.5 s
    assert ConnectLimits(jitter=0.999).jitter == 0.999
    assert ConnectLimits(start_rate=float("inf")).start_offset(999) == 0.0


@pytest.mark.parametrize(
    ("line", "said"),
    [
        ("max_connecting = 0", "max_connecting: must be a positive integer, not 0"),
        ("max_connecting_per_host = 2.5", "max_connecting_per_host: must be a positive integer"),
        ("start_rate = 0", "start_rate: must be a positive number of buses a second, not 0"),
        ("start_rate = nan", "start_rate: must be a positive number of buses a second, not nan"),
        ("jitter = 1", "jitter: must be a fraction in [0, 1), not 1"),
        ("jitter = -0.1", "jitter: must be a fraction in [0, 1), not -0.1"),
        ("lateness = 0", "lateness: must be a fraction in (0, 0.5], not 0"),
        ("lateness = 0.51", "lateness: must be a fraction in (0, 0.5], not 0.51"),
        ("lateness = true", "lateness: must be a fraction in (0, 0.5], not True"),
        ("retries = 3", "retries: unknown key (known: max_connecting, max_connecting_per_host"),
    ],
)
def test_connect_table_errors_name_file_line_and_key(line: str, said: str) -> None:
    filler = "jitter = 0.2" if not line.startswith("jitter") else "start_rate = 10"
    text = BUS + POINT + "\n[connect]\n" + filler + "\n" + line + "\n"
    with pytest.raises(ConfigError) as info:
        parse_config(text, "p.toml")
    # the line of the key: the last of the text
    assert str(info.value).startswith(f"p.toml:{len(text.splitlines())}: connect: {said}")


def test_connect_must_be_a_table() -> None:
    with pytest.raises(ConfigError, match=r"p\.toml: connect: must be a table"):
        parse_config("connect = 3\n" + BUS + POINT, "p.toml")


def test_network_buses_reconnect_with_the_connect_jitter() -> None:
    point = Point("x", "t", 1, "holding", 0)
    serial = Point("y", "s", 1, "holding", 0)
    buses = [Bus("t", "tcp://127.0.0.1:1502"), Bus("s", "/dev/pyrtu-no-such-port")]
    poller = Poller(make_config(buses, [point, serial]), connect=ConnectLimits(jitter=0.3))
    assert poller._runs["t"].reconnect.backoff.jitter == 0.3
    assert poller._runs["s"].reconnect.backoff.jitter == 0.1  # a serial port's: as before
    assert poller.descriptors == 2


# ---------------------------------------------------------------- the event loop


def test_more_descriptors_than_select_takes_get_the_epoll_loop() -> None:
    for descriptors, chosen in ((SELECT_LIMIT, selectors.SelectSelector),
                                (SELECT_LIMIT + 1, selectors.EpollSelector)):  # fmt: skip
        loop = new_event_loop(descriptors)
        try:
            assert type(loop._selector) is chosen  # type: ignore[attr-defined]
        finally:
            loop.close()


def test_a_loop_for_1100_descriptors_watches_them_all() -> None:
    """select() takes no descriptor above 1023: 1100 connections (2200 descriptors)
    are watched by the loop `run` picks for them."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = 2400
    if soft < need:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(need, hard), hard))
    try:

        async def main() -> int:
            loop = asyncio.get_running_loop()
            pairs = [socket.socketpair() for _ in range(1100)]
            try:
                woke: asyncio.Future[int] = loop.create_future()
                last = pairs[-1][0]
                loop.add_reader(last.fileno(), lambda: woke.set_result(last.fileno()))
                pairs[-1][1].send(b"x")
                try:
                    return await asyncio.wait_for(woke, 10)
                finally:
                    loop.remove_reader(last.fileno())
            finally:
                for a, b in pairs:
                    a.close()
                    b.close()

        assert aio_run(main(), descriptors=1100) > 1024
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


# ---------------------------------------------------------------- connects bounded


class SlowPort:
    """A listening port whose accept queue is full: a connect to it stays in
    progress (its SYN dropped) until the connecting side gives up."""

    def __init__(self, host: str = "127.0.0.1") -> None:
        self.sock = socket.socket()
        self.sock.bind((host, 0))
        self.sock.listen(0)
        self.port = int(self.sock.getsockname()[1])
        self.fillers = []
        for _ in range(3):
            filler = socket.socket()
            filler.setblocking(False)
            filler.connect_ex((host, self.port))
            self.fillers.append(filler)

    def close(self) -> None:
        for s in (*self.fillers, self.sock):
            s.close()


@pytest.fixture
def slow_ports() -> Iterator[Callable[[str], SlowPort]]:
    made: list[SlowPort] = []

    def make(host: str = "127.0.0.1") -> SlowPort:
        made.append(SlowPort(host))
        return made[-1]

    yield make
    for port in made:
        port.close()


def slow_config(ports: list[tuple[str, int]]) -> list[Bus]:
    return [Bus(f"b{i}", f"tcp://{host}:{port}", {"timeout": 2.0}) for i, (host, port) in
            enumerate(ports)]  # fmt: skip


def points_of(buses: list[Bus], interval: float = 1.0) -> list[Point]:
    return [Point(f"{b.name}.x", b.name, 1, "holding", 0, interval=interval) for b in buses]


def test_connects_in_progress_are_bounded(slow_ports: Callable[[str], SlowPort]) -> None:
    """Twelve connects that never complete: three in progress at once, no more."""
    buses = slow_config([("127.0.0.1", slow_ports("127.0.0.1").port) for _ in range(12)])
    limits = ConnectLimits(max_connecting=3, max_connecting_per_host=100, start_rate=1000)

    async def main() -> tuple[int, int]:
        poller = Poller(make_config(buses, points_of(buses)), connect=limits)
        async with poller:
            gate = poller._gate
            await until(lambda: gate.connecting == 3 and gate.waited >= 9, "three connecting")
            await asyncio.sleep(0.5)  # the others wait their turn meanwhile
            return gate.most, gate.connecting

    assert asyncio.run(main()) == (3, 3)


def test_connects_to_one_host_are_bounded(slow_ports: Callable[[str], SlowPort]) -> None:
    """Six slow ports on each of two loopback hosts: two connects at once per host."""
    hosts = ("127.0.0.1", "127.0.0.2")
    buses = slow_config([(h, slow_ports(h).port) for h in hosts for _ in range(6)])
    limits = ConnectLimits(max_connecting=10, max_connecting_per_host=2, start_rate=1000)

    async def main() -> tuple[int, dict[str, int]]:
        poller = Poller(make_config(buses, points_of(buses)), connect=limits)
        async with poller:
            gate = poller._gate
            await until(lambda: gate.connecting == 4, "two connecting to each host")
            await asyncio.sleep(0.5)
            return gate.most, dict(gate.most_per_host)

    assert asyncio.run(main()) == (4, {"127.0.0.1": 2, "127.0.0.2": 2})


@pytest.mark.wall_clock
def test_the_start_is_staggered() -> None:
    """20 devices at 40 buses a second: the k-th connects and polls first no sooner
    than k / 40 s after the start (its place in the start), all within the patience."""
    store = DataStore()
    store.holding_registers.add_range(0, [5])
    rate = 40.0

    async def main() -> tuple[float, dict[str, float]]:
        servers = [await TcpServer.for_store(1, store).start("127.0.0.1", 0) for _ in range(20)]
        buses = [Bus(f"b{i}", "tcp://{}:{}".format(*s.address), {"timeout": 2.0})
                 for i, s in enumerate(servers)]  # fmt: skip
        first: dict[str, float] = {}

        def answered(bus: str, slave: int, seconds: float) -> None:
            first.setdefault(bus, time.monotonic())

        poller = Poller(
            make_config(buses, points_of(buses)), connect=ConnectLimits(start_rate=rate)
        )
        poller.on_latency(answered)
        try:
            start = time.monotonic()
            async with poller:
                await until(lambda: len(first) == 20, "every device answered")
        finally:
            for s in servers:
                await s.close()
        return start, first

    start, first = asyncio.run(main())
    for k in range(20):
        # asyncio may run a timer up to its clock resolution early: 5 ms of slack
        assert first[f"b{k}"] >= start + k / rate - 0.005, (k, first[f"b{k}"] - start)


@pytest.mark.wall_clock
def test_a_slow_rtu_over_tcp_host_holds_up_no_other_bus(
    slow_ports: Callable[[str], SlowPort],
) -> None:
    """An ``rtu+tcp://`` host whose connect never completes (pyserial waits 5 s for
    it, again at every retry): opened on a worker thread, it holds up no other bus."""
    store = DataStore()
    store.holding_registers.add_range(0, [5])
    slow = slow_ports("127.0.0.1")

    async def main() -> list[float]:
        server = await TcpServer.for_store(1, store).start("127.0.0.1", 0)
        buses = [
            Bus("fast", "tcp://{}:{}".format(*server.address), {"timeout": 2.0}),
            Bus("slow", f"rtu+tcp://127.0.0.1:{slow.port}", {"timeout": 2.0}),
        ]
        points = [Point(f"{b.name}.x", b.name, 1, "holding", 0, interval=0.1) for b in buses]
        times: list[float] = []
        poller = Poller(make_config(buses, points))
        poller.on_latency(
            lambda bus, _, __: times.append(time.monotonic()) if bus == "fast" else None
        )
        try:
            async with poller:
                await until(lambda: len(times) >= 40, "40 reads of the fast bus")
        finally:
            await server.close()
        return times

    times = asyncio.run(main())
    gaps = [b - a for a, b in itertools.pairwise(times)]
    # a connect on the event loop stops every bus for its 5 s (50 intervals)
    assert max(gaps) < 2.0, max(gaps)


# ---------------------------------------------------------------- the short benchmark

REGISTERS = 10
HEALTHY = 47
INTERVAL = 0.25
TIMEOUT = 2.0  # every bus's; the silent device's reads end after it


def template(path: Path) -> Path:
    lines = ["[device]", 'vendor = "test"', 'model = "many"', "address = 1", ""]
    for i in range(REGISTERS):
        lines += ["[[point]]", f'name = "r{i}"', 'table = "holding"', f"address = {i}", ""]
    path.write_text("\n".join(lines))
    return path


@pytest.fixture
def devices(tmp_path: Path) -> Iterator[int]:
    """47 devices of 10 registers on consecutive ports, one ``pyrtu simulate`` process."""
    path = template(tmp_path / "many.toml")
    for _ in range(5):
        first = free_port_range(HEALTHY)
        spec = f"127.0.0.1:{first}-{first + HEALTHY - 1}"
        bg = Background("simulate", "--template", path, "--tcp", spec, "--json")
        try:
            assert json.loads(bg.line(timeout=60))["type"] == "ready"
        except Exception:
            result = bg.finish()
            if "cannot listen" in result.err:
                continue
            raise AssertionError(result.err) from None
        try:
            yield first
        finally:
            bg.kill()
        return
    raise AssertionError("no range of ports could be bound")


@pytest.mark.wall_clock
@pytest.mark.parametrize("master", ["auto", "aio"])
def test_fifty_devices_one_silent_one_refusing_one_slow_the_others_keep_their_period(
    devices: int, slow_ports: Callable[[str], SlowPort], master: str
) -> None:
    """On the mux (``auto``: `pyrtu.poller.muxdrive`) and on a master per bus."""
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen(8)  # accepts (the kernel does), never reads, never answers
    with socket.socket() as gone:
        gone.bind(("127.0.0.1", 0))
        refusing = int(gone.getsockname()[1])  # nothing listens there once closed
    slow = slow_ports("127.0.0.1")
    bad = {
        "silent": int(silent.getsockname()[1]),
        "refusing": refusing,
        "slow": slow.port,
    }
    urls = {f"d{i}": f"tcp://127.0.0.1:{devices + i}" for i in range(HEALTHY)}
    urls.update({name: f"tcp://127.0.0.1:{port}" for name, port in bad.items()})
    names = list(urls)
    random.Random(3).shuffle(names)  # the bad ones somewhere among the others
    buses = [Bus(n, urls[n], {"timeout": TIMEOUT}) for n in names]
    points = [Point(f"{b.name}.r{r}", b.name, 1, "holding", r, interval=INTERVAL)
              for b in buses for r in range(REGISTERS)]  # fmt: skip
    answers: dict[str, list[float]] = {n: [] for n in names}
    downs: list[str] = []

    async def main() -> None:
        poller = Poller(
            make_config(buses, points), connect=ConnectLimits(max_connecting=4), master=master
        )
        assert {r.on_mux for r in poller._runs.values()} == {master == "auto"}
        poller.on_latency(lambda bus, slave, seconds: answers[bus].append(time.monotonic()))
        poller.on_event(
            lambda ev: downs.append(ev.bus) if isinstance(ev, PortState) and not ev.up else None
        )
        async with poller:
            # every healthy device polled 16 times (4 s at 4 Hz), the bad ones meanwhile
            await until(lambda: all(len(answers[f"d{i}"]) >= 17 for i in range(HEALTHY)),
                        "16 periods of every healthy device")  # fmt: skip

    try:
        asyncio.run(main())
    finally:
        silent.close()
    assert not answers["silent"] and not answers["refusing"] and not answers["slow"]
    assert set(downs) == {"refusing", "slow"}  # (a silent device's port is up: it accepted)
    periods = []
    for i in range(HEALTHY):
        times = answers[f"d{i}"][1:17]  # from the first poll on the beat
        gaps = [b - a for a, b in itertools.pairwise(times)]
        periods.append(statistics.mean(gaps) / INTERVAL)
        # a device held up by a bad one would miss its beat by the bad one's timeout
        # (8 intervals): a gap of 4 intervals is a loaded machine's, not that
        assert max(gaps) < 4 * INTERVAL, (i, gaps)
    # each healthy device's period: its interval (a loaded machine: within 25 %)
    assert all(0.75 <= p <= 1.25 for p in periods), periods


# ---------------------------------------------------------------- wake-ups shared


def test_network_polls_wake_on_a_grid_of_their_interval() -> None:
    """A thousand devices at 1 Hz started a millisecond apart would wake the loop a
    thousand times a second, one bus each: a network bus's polls wake on a grid of
    ``lateness`` (2.5 %) of its shortest interval (at most 25 ms), so those due
    within one tick share a wake-up; a local bus's wake at their due time."""
    assert wake_tick(1.0) == 0.025
    assert wake_tick(0.5) == 0.0125
    assert wake_tick(2.0) == 0.025  # at most a second's
    assert wake_tick(0.5, 0.01) == 0.005 and wake_tick(60.0, 0.01) == 0.01
    buses = [Bus("t", "tcp://127.0.0.1:1502"), Bus("s", "/dev/pyrtu-no-such-port")]
    points = [
        Point("t.x", "t", 1, "holding", 0, interval=2.0),
        Point("t.y", "t", 1, "holding", 1, interval=0.5),  # the shortest: its 1 %
        Point("s.x", "s", 1, "holding", 0, interval=0.5),
    ]
    assert Poller(make_config(buses, points))._runs["t"].tick == 0.0125
    poller = Poller(make_config(buses, points), connect=ConnectLimits(lateness=0.01))
    network, local = poller._runs["t"], poller._runs["s"]
    assert network.tick == 0.005 and local.tick == 0.0
    # the boundaries: on a grid point (as the arithmetic of due times gives it) at
    # once, just past it the next one, just before it that one
    assert network.wake_at(100.005) == 100.005
    assert network.wake_at(0.1 + 0.2) == 0.1 + 0.2  # 0.30000000000000004: on 0.300
    assert network.wake_at(100.0051) == pytest.approx(100.010, abs=1e-9)
    assert network.wake_at(100.0049) == pytest.approx(100.005, abs=1e-9)
    assert local.wake_at(100.0051) == 100.0051
    assert network.wake_at(float("-inf")) == float("-inf")  # something due now


@pytest.mark.wall_clock
def test_a_refusing_device_is_retried_on_its_back_off_and_holds_no_connect() -> None:
    """A device that refuses is tried again only after its back-off (no jitter:
    0.1 s doubling to 0.4 s, so never more often than that schedule allows), and
    with one connect at a time in the whole poller the healthy devices still
    connect and poll: the refusal gives its slot back at once."""
    store = DataStore()
    store.holding_registers.add_range(0, [5])
    with socket.socket() as gone:
        gone.bind(("127.0.0.1", 0))
        refusing = int(gone.getsockname()[1])
    waits = [0.1, 0.2, 0.4]  # then 0.4 each time
    limits = ConnectLimits(max_connecting=1, max_connecting_per_host=1, jitter=0.0)

    async def main() -> tuple[int, float, dict[str, int]]:
        servers = [await TcpServer.for_store(1, store).start("127.0.0.1", 0) for _ in range(4)]
        buses = [Bus(f"b{i}", "tcp://{}:{}".format(*s.address), {"timeout": 2.0})
                 for i, s in enumerate(servers)]  # fmt: skip
        buses.append(
            Bus("bad", f"tcp://127.0.0.1:{refusing}", {"timeout": 2.0}, backoff=0.1,
                max_backoff=0.4)
        )  # fmt: skip
        answers = {b.name: 0 for b in buses}

        def answered(bus: str, slave: int, seconds: float) -> None:
            answers[bus] += 1

        poller = Poller(make_config(buses, points_of(buses, 0.1)), connect=limits)
        poller.on_latency(answered)
        try:
            async with poller:
                bad = poller._runs["bad"].reconnect  # (start makes it anew)
                await until(lambda: bad.outage is not None and bad.outage.attempts >= 6,
                            "six attempts to connect to the refusing port")  # fmt: skip
                await until(lambda: min(answers[f"b{i}"] for i in range(4)) >= 20,
                            "20 reads of every healthy device")  # fmt: skip
                outage = bad.outage
                assert outage is not None
                return outage.attempts, time.monotonic() - outage.since, answers
        finally:
            for s in servers:
                await s.close()

    attempts, elapsed, answers = asyncio.run(main())
    assert answers["bad"] == 0
    # the k-th attempt after the first comes no sooner than the sum of k waits
    allowed, passed = 1, 0.0
    while True:
        passed += waits[min(allowed - 1, len(waits) - 1)]
        if passed > elapsed:
            break
        allowed += 1
    assert 6 <= attempts <= allowed, (attempts, allowed, elapsed)


def test_change_only_delivery_skips_no_change_and_keeps_every_one() -> None:
    """A value read again unchanged is recognised without `Point.changed` (the
    common case): what `Tracker.offer` delivers is still exactly what the rule of
    docs/POLLER.md says, equal values of another type and NaN included."""
    plain = Point("p", "b", 1, "holding", 0)
    banded = Point("q", "b", 1, "holding", 1, deadband=2)
    nan = math.nan
    cases = [
        (plain, [5, 5, 6, 6, True, 1, 1.0, 1.0, 0.0, -0.0, nan, nan, 2.5, "a", "a", "b"],
         [True, False, True, False, True, True, True, False, True, False, True, False, True,
          True, False, True]),
        # within the deadband of the last *delivered* value, more than it, exactly it
        (banded, [10, 12, 13, 11, 16, 16.0, 18.0], [True, False, True, False, True, True, False]),
    ]  # fmt: skip
    for point, values, delivered in cases:
        tracker = Tracker()
        got = [tracker.offer(Update(point, v, 0.0), float(i)) for i, v in enumerate(values)]
        assert got == delivered, (point.name, values)
        assert tracker.last(point.name) == Update(point, values[-1], 0.0)
        assert tracker.age(point.name, 100.0) == 100.0 - (len(values) - 1)
