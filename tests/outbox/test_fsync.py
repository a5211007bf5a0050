"""The outbox's fsync batches run off the event loop (pyrtu/outbox/_sync.py):
on a dedicated thread, one batch at a time, the records published from the outbox
only once durable, a failed batch reported and flushed again, SIGKILL losing at
most the batch not yet synced, and the thread joined when the bridge stops.

The fsyncs are real: ``os.fdatasync`` and ``os.fsync`` are wrapped (the seam) to
note the thread each runs on, then called."""

from __future__ import annotations

import asyncio
import errno
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mqtt_broker import Broker
from outbox_helpers import SMALL, everything, payload

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge
from pyrtu.drivers.aio import run as aio_run
from pyrtu.outbox._sync import Flusher
from pyrtu.outbox.outbox import Outbox, OutboxError, OutboxLimits
from pyrtu.poller import Point, Update

#: a safety net, not a measurement: conditions are awaited, never timed
PATIENCE = 30.0


class Syncs:
    """os.fdatasync and os.fsync wrapped: the thread of every call, then the call."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.threads: list[int] = []
        self.fail: OSError | None = None
        for name in ("fdatasync", "fsync"):
            real = getattr(os, name)
            monkeypatch.setattr(os, name, self._wrap(real))

    def _wrap(self, real: Callable[[int], None]) -> Callable[[int], None]:
        def call(fd: int) -> None:
            self.threads.append(threading.get_ident())
            if self.fail is not None:
                raise self.fail
            real(fd)

        return call

    def on(self, ident: int) -> int:
        return sum(1 for t in self.threads if t == ident)


async def until(condition: Callable[[], bool], what: str) -> None:
    give_up = time.monotonic() + PATIENCE
    while not condition():
        assert time.monotonic() < give_up, f"gave up waiting for {what}"
        await asyncio.sleep(0.005)


def test_flusher_fsyncs_on_its_thread_and_publishes_only_durable_records(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ob = Outbox(tmp_path / "ob", OutboxLimits(fsync_interval=0.01, segment_bytes=4096))
    syncs = Syncs(monkeypatch)
    results: list[OutboxError | None] = []

    async def main() -> tuple[int, threading.Thread | None]:
        loop_thread = threading.get_ident()
        flusher = Flusher(ob, results.append)
        flusher.start()
        thread = flusher._thread
        seqs = []
        for round_ in range(20):
            for _ in range(50):  # several segments: sealed ones are synced too
                seqs.append(ob.append(payload(ob.next_seq), time.monotonic()))
                flusher.poke()
            assert ob.pending(1, after=seqs[-2]) == []  # not durable yet: not readable
            await until(lambda: ob.durable_seq >= seqs[-1], f"round {round_} durable")
            assert [s for s, _ in everything(ob, seqs[0] - 1)] == seqs
        await flusher.stop()
        return loop_thread, thread

    loop_thread, thread = aio_run(main())
    assert thread is not None and not thread.is_alive()  # joined
    assert syncs.on(loop_thread) == 0, "an fsync ran on the event loop's thread"
    assert len(syncs.threads) >= 20 and set(syncs.threads) == {thread.ident}
    assert results and all(r is None for r in results)
    ob.close()


def test_a_failed_batch_is_reported_and_flushed_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fails the fsync (ENOSPC, then it works again): the error reaches the
    loop, nothing is durable meanwhile, and the next batch syncs every record."""
    ob = Outbox(tmp_path / "ob", SMALL)
    syncs = Syncs(monkeypatch)
    results: list[OutboxError | None] = []

    async def main() -> None:
        flusher = Flusher(ob, results.append)
        flusher.start()
        first = [ob.append(payload(ob.next_seq), 0.0) for _ in range(300)]  # sealed segments
        syncs.fail = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        assert flusher.submit()
        await until(lambda: len(results) >= 2, "the failed batch, tried again")
        assert all(isinstance(r, OutboxError) and "disk is full" in str(r) for r in results)
        assert ob.durable_seq < first[0] and ob.pending(10) == []
        more = [ob.append(payload(ob.next_seq), 0.0) for _ in range(10)]
        syncs.fail = None  # the disk works again
        await until(lambda: results[-1] is None, "the next batch")
        assert ob.durable_seq == more[-1]
        assert [s for s, _ in everything(ob)] == first + more
        await flusher.stop()

    aio_run(main())
    ob.close()
    with Outbox(tmp_path / "ob", SMALL) as again:
        assert [s for s, p in everything(again)] == list(range(1, 311))
        assert all(p == payload(s) for s, p in everything(again))


CHILD = textwrap.dedent(
    """
    import asyncio, hashlib, os, sys
    from pyrtu.outbox._sync import Flusher
    from pyrtu.outbox.outbox import Outbox, OutboxLimits

    def payload(seq):
        return (hashlib.blake2b(str(seq).encode(), digest_size=32).digest() * 2)[: 1 + seq % 64]

    async def main():
        ob = Outbox(sys.argv[1], OutboxLimits(fsync_interval=0.005, segment_bytes=8192))
        def done(err):
            os.write(1, b"F %d\\n" % ob.durable_seq)
        flusher = Flusher(ob, done)
        flusher.start()
        os.write(1, b"R %d\\n" % ob.next_seq)
        while True:
            for _ in range(20):
                ob.append(payload(ob.next_seq), 0.0)
                flusher.poke()
            await asyncio.sleep(0)

    asyncio.run(main())
    """
)


@pytest.mark.parametrize("wait", [0.05, 0.2, 0.5])
def test_sigkill_with_the_flusher_thread_loses_no_durable_record(
    tmp_path: Path, wait: float
) -> None:
    """A child appends flat out and flushes on the thread; SIGKILL at some point:
    every record its loop was told durable is there, intact, in order."""
    d = tmp_path / "ob"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(d)], stdout=subprocess.PIPE, env=env)
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith(b"R ")
    time.sleep(wait)
    proc.send_signal(signal.SIGKILL)
    out = proc.stdout.read()
    proc.wait()
    durable = [int(ln.split()[1]) for ln in out.split(b"\n")[:-1] if ln.startswith(b"F ")]
    assert durable, "no batch finished before the kill"
    with Outbox(d) as ob:
        got = everything(ob)
        seqs = [s for s, _ in got]
        assert seqs[: durable[-1]] == list(range(1, durable[-1] + 1))
        assert seqs == list(range(1, len(seqs) + 1))  # a prefix: no hole, no reorder
        assert all(p == payload(s) for s, p in got)
        assert ob.next_seq > durable[-1]


def twenty_points(tmp_path: Path, mqtt: str) -> tuple[list[Point], str]:
    """Twenty holding registers of slave 1 on a bus that is not there, and the bridge
    configuration that publishes them (``mqtt``: more lines of its [mqtt] table; the
    broker's URL is "URL", to be replaced)."""
    points = [Point(f"p{i}", "bus", 1, "holding", i) for i in range(20)]
    text = (
        f'[mqtt]\nurl = "URL"\nedge = "e"\noutbox = "{tmp_path / "ob"}"\n{mqtt}\n'
        '[[bus]]\nname = "bus"\nport = "/dev/null"\nbaudrate = 115200\n'
    ) + "".join(
        f'[[point]]\nname = "{p.name}"\nbus = "bus"\nslave = 1\ntable = "holding"\n'
        f"address = {p.address}\n"
        for p in points
    )
    return points, text


def test_the_bridge_never_fsyncs_on_the_event_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A running bridge (a real broker, 2000 updates fed, acknowledged, the cursor
    saved): every fsync of the outbox on the flusher's thread; stop joins it."""
    points, text = twenty_points(tmp_path, "qos = 1\nfsync_interval = 0.01")
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(text.replace("URL", broker.url), "b.toml")

        async def main() -> tuple[int, int, Any, dict[str, Any]]:
            bridge = Bridge(cfg)
            await bridge.start(poll=False)
            syncs = Syncs(monkeypatch)  # from here: the running bridge
            await until(lambda: bool(bridge.stats()["connected"]), "connected")
            for i in range(2000):
                bridge.feed(Update(points[i % 20], i, time.time()))
                if i % 100 == 99:
                    await asyncio.sleep(0.005)
            await until(lambda: bridge.stats()["outbox_depth"] == 0, "every update acknowledged")
            await asyncio.sleep(0.05)  # the cursor's batch
            loop_thread = threading.get_ident()
            on_loop = syncs.on(loop_thread)
            total = len(syncs.threads)
            flusher = bridge._flusher
            assert flusher is not None
            thread = flusher._thread
            await bridge.stop()
            return on_loop, total, thread, bridge.final_stats

        on_loop, total, thread, stats = aio_run(main())
    assert on_loop == 0, f"{on_loop} fsyncs ran on the event loop's thread"
    assert total >= 2
    assert thread is not None and not thread.is_alive()
    assert stats["acknowledged"] >= 2000 and stats["drops"] == 0


def test_qos0_publications_are_acknowledged_once_written_without_paho_callbacks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At QoS 0 a publication is acknowledged (the outbox forgets it) once paho has
    written it, found through its MQTTMessageInfo, not through paho's on_publish,
    for which paho builds a ReasonCode and a Properties object per message (half
    the bridge's CPU per update at QoS 0): every update reaches a subscriber, the
    outbox empties, and paho builds no such pair per publication."""
    from mqtt_broker import Client
    from paho.mqtt.properties import Properties

    built = [0]
    real_init = Properties.__init__

    def counting(self: Any, *args: Any, **kw: Any) -> None:
        if threading.get_ident() == loop_thread[0]:  # the bridge's (not the subscriber's)
            built[0] += 1
        real_init(self, *args, **kw)

    loop_thread = [0]

    points, text = twenty_points(tmp_path, "qos = 0")
    with Broker(tmp_path) as broker:
        cfg = parse_bridge_config(text.replace("URL", broker.url), "b.toml")
        sub = Client(broker, ["pyrtu/e/bus/1/#"])

        async def main() -> dict[str, Any]:
            bridge = Bridge(cfg)
            await bridge.start(poll=False)
            await until(lambda: bool(bridge.stats()["connected"]), "connected")
            loop_thread[0] = threading.get_ident()
            monkeypatch.setattr(Properties, "__init__", counting)
            for i in range(2000):
                bridge.feed(Update(points[i % 20], i, time.time()))
                if i % 100 == 99:
                    await asyncio.sleep(0.005)
            await until(lambda: bridge.stats()["outbox_depth"] == 0, "every update written")
            stats = bridge.stats()
            monkeypatch.undo()
            await bridge.stop()
            return stats

        stats = aio_run(main())
        assert stats["published"] == stats["acknowledged"] >= 2000
        sub.wait(
            lambda: (
                sum(1 for t, *_ in list(sub.messages) if t.startswith("pyrtu/e/bus/1/p")) >= 2000
            ),
            "every update at the subscriber",
        )
        sub.close()
    assert built[0] < 100, f"{built[0]} paho Properties built by the bridge for 2000 publications"
