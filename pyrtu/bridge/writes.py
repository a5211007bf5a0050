"""The bridge's writes: set commands from the broker to the drives and their results.

`SetWriter.on_message` takes a message of a set topic, refuses it with a result when
it must (see `pyrtu.bridge.commands`) or queues it for its slave; one task per
slave with commands waiting writes them in turn, each when the slave's rate limit
lets it and only while it has not expired, through the poller's write queue
(ahead of every poll), reads the point back, publishes the value read back at
once and sends the result: to the command's MQTT 5 response topic with its
correlation data, else to ``{point topic}/set/result``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Protocol

import paho.mqtt.client as paho

from pyrtu.pdu.errors import ExceptionResponseError, ModbusError, NoResponseError

from ..drivers.reconnect import Backoff, Reconnect
from ..poller import Point, Poller
from ..poller.points import Value
from ..poller.values import faithful_value
from .commands import CommandQueue, Refusal, SetCommand, check_value, parse, result, rounding
from .config import BridgeConfig
from .mqtt import MqttLink, publish_properties
from .topics import Topics


class Host(Protocol):
    """What a `SetWriter` uses of its `pyrtu.bridge.Bridge`."""

    config: BridgeConfig
    topics: Topics
    poller: Poller
    commands: CommandQueue

    def publish_value(self, point: Point, value: Value | None, read_at: float) -> None: ...

    def task_failed(
        self, task: str, error: BaseException, retry_in: float, first: bool = True
    ) -> None: ...


log = logging.getLogger("pyrtu.bridge")


class SetWriter:
    """Set commands of one bridge (see the module docstring)."""

    def __init__(self, bridge: Host) -> None:
        self.bridge = bridge
        self.queue = bridge.commands
        self.cfg = bridge.config
        self._link: MqttLink | None = None
        self._workers: dict[tuple[str, int], asyncio.Task[None]] = {}
        self._retry = Reconnect(Backoff(self.cfg.mqtt.backoff, self.cfg.mqtt.max_backoff))
        self.received = 0
        self.ignored = 0  # empty payloads (retained commands cleared)
        self.refusals: dict[str, int] = {}
        self.failures = 0
        self.write_latency: list[float] = []
        self.last_write_at = 0.0  # when the last write's answer came (Unix)
        self.sent_to_written: list[float] = []  # commands with a "time": to the answer, s

    def connected(self, link: MqttLink) -> None:
        self._link = link

    async def stop(self) -> None:
        tasks = list(self._workers.values())
        for t in tasks:
            t.cancel()
        for t, outcome in zip(
            tasks, await asyncio.gather(*tasks, return_exceptions=True), strict=True
        ):
            if isinstance(outcome, Exception):  # _work reports its failures: a bug
                log.error("bridge: task %s ended with %r", t.get_name(), outcome)
        self._workers.clear()

    def stats(self) -> dict[str, Any]:
        q = self.queue
        return {
            "received": self.received,
            "ignored": self.ignored,
            "executed": q.executed,
            "expired": q.expired,
            "duplicates": q.duplicates,
            "busy": q.refused,
            "failed": self.failures,
            "refused": dict(self.refusals),
            "waiting": q.waiting,
        }

    # ------------------------------------------------------------------ arrival

    def on_message(self, msg: paho.MQTTMessage) -> None:
        self.received += 1
        now = time.monotonic()
        topic = msg.topic
        props = getattr(msg, "properties", None)
        reply = getattr(props, "ResponseTopic", None) or topic + "/result"
        corr = getattr(props, "CorrelationData", None)
        if not msg.payload:  # no command: a retained one cleared (mosquitto_pub -r -n)
            self._ignore(topic)
            return
        name = self.bridge.topics.set.get(topic)
        if name is None:
            self._refuse(
                Refusal("unknown_point", f"no point has the set topic {topic!r}"), None, reply, corr
            )
            return
        point = self.bridge.poller.point(name)
        if not point.writable:
            self._refuse(
                Refusal(
                    "not_writable",
                    f"point {name!r} is not writable (set writable = true in its [[point]] table)",
                ),
                name,
                reply,
                corr,
            )
            return
        parsed = parse(
            bytes(msg.payload), max_payload=self.cfg.mqtt.max_payload, retained=msg.retain
        )
        if parsed is None:
            self._ignore(topic)
            return
        if isinstance(parsed, Refusal):
            self._refuse(parsed, name, reply, corr)
            return
        value, cid, sent = parsed
        if cid is None and corr is not None:
            cid = "corr:" + bytes(corr).hex()
        seen, res = self.queue.known(cid)
        if seen:
            if res is not None:
                self._reply(reply, res, corr)
            return
        try:
            encoded = check_value(point, value)
        except ValueError as e:
            self._refuse(Refusal("validation", str(e), cid), name, reply, corr)
            return
        rounded = rounding(point, value, encoded)
        expiry = getattr(props, "MessageExpiryInterval", None)
        life = float(expiry) if expiry is not None else self.cfg.mqtt.command_expiry
        expires = now + life
        if sent is not None:
            expires = min(expires, now + (sent + self.cfg.mqtt.command_expiry - time.time()))
        cmd = SetCommand(
            point,
            encoded.value,
            cid,
            expires,
            now,
            reply,
            None if corr is None else bytes(corr),
            sent,
            rounded,
        )
        if now >= expires:
            self.queue.expired += 1
            self._finish(
                cmd,
                result(
                    name,
                    False,
                    id=cid,
                    error="expired",
                    message="the command had expired when it arrived",
                ),
            )
            return
        if not self.queue.push(cmd):
            self._refuse(
                Refusal("busy", f"{self.queue.size} commands are waiting; try later", cid),
                name,
                reply,
                corr,
            )
            return
        key = (point.bus, point.slave)
        if key not in self._workers:
            self._workers[key] = asyncio.get_running_loop().create_task(
                self._work(key), name=_worker_name(key)
            )

    def command(self, name: str, value: object, origin: str) -> Refusal | None:
        """A command that comes by another road than a set topic (a Sparkplug DCMD,
        ``origin`` naming it in the log): the same checks (the point known and
        writable, the value's type and range), queue, rate limit, expiry, write and
        read-back (`Host.publish_value`) as a set topic's; the result is logged, not
        published (no reply topic).  The `Refusal` when it is refused (counted and
        logged), else None."""
        self.received += 1
        now = time.monotonic()
        refusal: Refusal | None = None
        point = None
        try:
            point = self.bridge.poller.point(name)
        except KeyError:
            refusal = Refusal("unknown_point", f"no point named {name!r}")
        if point is not None and not point.writable:
            refusal = Refusal("not_writable", f"point {name!r} is not writable")
        if point is not None and refusal is None:
            try:
                encoded = check_value(point, value)
            except ValueError as e:
                refusal = Refusal("validation", str(e))
            else:
                cmd = SetCommand(
                    point,
                    encoded.value,
                    None,
                    now + self.cfg.mqtt.command_expiry,
                    now,
                    "",
                    rounded=rounding(point, value, encoded),
                )
                if not self.queue.push(cmd):
                    refusal = Refusal("busy", f"{self.queue.size} commands are waiting")
        if refusal is not None:
            self.refusals[refusal.error] = self.refusals.get(refusal.error, 0) + 1
            log.warning("bridge: %s refused (%s): %s", origin, refusal.error, refusal.message)
            return refusal
        assert point is not None
        key = (point.bus, point.slave)
        if key not in self._workers:
            self._workers[key] = asyncio.get_running_loop().create_task(
                self._work(key), name=_worker_name(key)
            )
        return None

    def _ignore(self, topic: str) -> None:
        self.ignored += 1
        log.debug("bridge: empty payload on %s ignored (a retained message cleared)", topic)

    def _refuse(self, r: Refusal, point: str | None, reply: str, corr: Any) -> None:
        self.refusals[r.error] = self.refusals.get(r.error, 0) + 1
        log.info("bridge: set command refused (%s): %s", r.error, r.message)
        self._reply(reply, result(point, False, id=r.id, error=r.error, message=r.message), corr)

    def _reply(self, topic: str, body: bytes, corr: Any) -> None:
        if not topic:  # a command without a reply topic (`command`): its result logged
            log.info("bridge: command result: %s", body.decode("utf-8", "replace"))
            return
        link = self._link
        if link is None or not link.connected:
            return
        props = publish_properties(correlation=bytes(corr)) if corr is not None else None
        try:
            link.publish(topic, body, 1, False, props)
        except ValueError as e:  # a response topic with wildcards
            log.info("bridge: cannot answer on %r: %s", topic, e)

    def _finish(self, cmd: SetCommand, body: bytes) -> None:
        self.queue.done(cmd.id, body)
        self._reply(cmd.reply_to, body, cmd.correlation)

    # ------------------------------------------------------------------ execution

    async def _work(self, key: tuple[str, int]) -> None:
        """The slave's commands in turn.  A command whose execution raises what no
        transaction raises (a fault of the bridge) is answered ``failed``, the fault
        reported (`Host.task_failed`), and the next command waits the shared
        back-off: the slave is never left deaf to commands."""
        try:
            while (cmd := self.queue.pop(key)) is not None:
                try:
                    await self._execute(key, cmd)
                except Exception as e:
                    self.failures += 1
                    now = time.monotonic()
                    first = self._retry.failed(now, e)
                    wait = self._retry.wait(now)
                    self.bridge.task_failed(_worker_name(key), e, wait, first)
                    self._finish(
                        cmd,
                        result(
                            cmd.point.name,
                            False,
                            id=cmd.id,
                            error="failed",
                            message=f"internal error: {type(e).__name__}: {e}",
                        ),
                    )
                    await asyncio.sleep(wait)
                else:
                    self._retry.recovered(time.monotonic())
        finally:
            self._workers.pop(key, None)

    async def _execute(self, key: tuple[str, int], cmd: SetCommand) -> None:
        name = cmd.point.name
        bucket = self.queue.bucket(key, time.monotonic())
        late = False
        while (wait := bucket.wait(time.monotonic())) > 0:
            if time.monotonic() + wait >= cmd.expires:
                late = True  # its turn comes after its expiry
                break
            await asyncio.sleep(wait)
        if late or time.monotonic() >= cmd.expires:
            self.queue.expired += 1
            self._finish(
                cmd,
                result(
                    name, False, id=cmd.id, error="expired", message="expired before its turn came"
                ),
            )
            return
        poller = self.bridge.poller
        try:
            how = await poller.write(name, cmd.value)
            self.last_write_at = time.time()
            self.write_latency.append(time.monotonic() - cmd.received)
            del self.write_latency[:-1024]
            if cmd.sent is not None:  # from the sender's clock to the write's answer
                self.sent_to_written.append(self.last_write_at - cmd.sent)
                del self.sent_to_written[:-1024]
            value = await poller.read(name)
        except ExceptionResponseError as e:
            self.failures += 1
            self._finish(
                cmd,
                result(
                    name, False, id=cmd.id, error="exception", message=str(e), exception_code=e.code
                ),
            )
            return
        except NoResponseError as e:
            self.failures += 1
            self._finish(cmd, result(name, False, id=cmd.id, error="timeout", message=str(e)))
            return
        except (ModbusError, OSError, ValueError, RuntimeError) as e:
            self.failures += 1
            self._finish(cmd, result(name, False, id=cmd.id, error="failed", message=str(e)))
            return
        self.queue.executed += 1
        now = time.time()
        self.bridge.publish_value(cmd.point, value, now)
        if cmd.rounded is not None:
            log.info(
                "bridge: set %s: %r rounded to %r (its resolution)",
                name,
                cmd.rounded["requested"],
                cmd.rounded["written"],
            )
        shown = faithful_value(cmd.point, value)
        method = None if how == "write" else how  # a bit or field: FC 22 or read-modify-write
        self._finish(
            cmd,
            result(
                name, True, id=cmd.id, value=shown, time=now, rounded=cmd.rounded, method=method
            ),
        )


def _worker_name(key: tuple[str, int]) -> str:
    return f"pyrtu-bridge-writes-{key[0]}-{key[1]}"


__all__ = ["SetWriter"]
