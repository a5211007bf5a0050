"""Set commands through a real mosquitto to the simulated CFW701 on the virtual
bus: written ahead of the polls, read back, the value published at once, the
result on ``/set/result`` or the MQTT 5 response topic with its correlation
data; repeated ids executed once; bad commands refused with a result saying why
and nothing sent; expired commands never executed; a flood bounded."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from bridge_configs import weg_on_line
from mqtt_broker import Broker, Client
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from pyrtu.bridge import parse_bridge_config
from pyrtu.bridge.bridge import Bridge
from pyrtu.devices import CFW701Simulator, weg
from pyrtu.drivers._loopthread import LoopThread

vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 115200
BASE = "pyrtu/e1/line/1"


#: a write that times out under load is tried again (FC 06 is idempotent): these
#: tests are about what a set command does, not about the bus's timing
RETRIES = "retries = 2\n"


def config(url: str, port: str, outbox: Path, extra: str = "", points: str = "") -> str:
    return f"""
[mqtt]
url = "{url}"
edge = "e1"
outbox = "{outbox}"
command_expiry = 5
{extra}
{weg_on_line(port, 0.05, RETRIES)}[[point]]
name = "weg.ref"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_REFERENCE}
writable = true
min = 0
max = 8192
interval = 1
[[point]]
name = "weg.speed_rw"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_MOTOR_SPEED}
writable = true
interval = 1
{points}"""


#: a scaled view of the reference (tenths), for the sets that round
TENTHS = f"""
[[point]]
name = "weg.ref_tenths"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_REFERENCE}
scale = 0.1
writable = true
interval = 1
"""


@contextlib.contextmanager
def rig(
    tmp: Path, extra: str = "", points: str = ""
) -> Iterator[tuple[Broker, CFW701Simulator, Bridge, Client]]:
    with Broker(tmp) as broker, vbus.VirtualBus(2, baudrate=BAUD, parity="N") as bus:
        sim = CFW701Simulator()
        sim.serve(bus.paths[1], 1, baudrate=BAUD, parity="N")
        try:
            text = config(broker.url, bus.paths[0], tmp / "ob", extra, points)
            cfg = parse_bridge_config(text, "b.toml")
            bridge = Bridge(cfg)
            thread = LoopThread("bridge", bridge.start, bridge.stop)
            thread.start()
            try:
                with Client(broker, ["pyrtu/e1/#"]) as cl:
                    cl.wait(lambda: bool(cl.on(f"{BASE}/weg.ref")), "the bridge publishing")
                    yield broker, sim, bridge, cl
            finally:
                thread.stop()
        finally:
            sim.close()


def results(cl: Client, point: str = "weg.ref") -> list[dict[str, Any]]:
    return [json.loads(p) for p in cl.on(f"{BASE}/{point}/set/result")]


def wait_results(cl: Client, n: int, point: str = "weg.ref") -> list[dict[str, Any]]:
    cl.wait(lambda: len(results(cl, point)) >= n, f"{n} results")
    return results(cl, point)


def ref(sim: CFW701Simulator) -> int:
    return int(sim.store.holding_registers.get(weg.P_REFERENCE))


def test_a_write_is_read_back_published_and_answered(tmp_path: Path) -> None:
    with rig(tmp_path) as (_b, sim, _bridge, cl):
        cl.publish(f"{BASE}/weg.ref/set", b'{"value": 1000, "id": "a1"}')
        (res,) = wait_results(cl, 1)
        assert res == {
            "ok": True,
            "point": "weg.ref",
            "id": "a1",
            "value": 1000,
            "time": res["time"],
        }
        assert ref(sim) == 1000
        # the value read back is published at once, as good
        cl.wait(lambda: json.loads(cl.on(f"{BASE}/weg.ref")[-1])["value"] == 1000, "read-back")
        # the same id again, another value: executed once, the result sent again
        cl.publish(f"{BASE}/weg.ref/set", b'{"value": 2000, "id": "a1"}')
        again = wait_results(cl, 2)[1]
        assert again == res and ref(sim) == 1000
        # a bare value, and the MQTT 5 response topic with its correlation data
        props = Properties(PacketTypes.PUBLISH)
        props.ResponseTopic = "client/replies"
        props.CorrelationData = b"\x01req-7"
        with Client(_b, ["client/replies"]) as asker:
            asker.publish(f"{BASE}/weg.ref/set", b"3000", properties=props)
            asker.wait(lambda: bool(asker.messages), "the reply")
            topic, body, _retain, rprops, _t = asker.messages[0]
        assert topic == "client/replies" and json.loads(body)["ok"] is True
        assert rprops.CorrelationData == b"\x01req-7"  # type: ignore[attr-defined]
        assert ref(sim) == 3000


@pytest.mark.parametrize(
    ("topic", "payload", "retain", "error"),
    [
        ("weg.ref", b'{"value": 9000}', False, "validation"),  # above max
        ("weg.ref", b'{"value": -1}', False, "validation"),  # below min
        ("weg.ref", b'"fast"', False, "validation"),  # not a number
        ("weg.ref", b"true", False, "validation"),  # a bool is no number here
        ("weg.ref", b"{nope", False, "malformed"),
        ("weg.ref", b'{"value": 1, "extra": 2}', False, "malformed"),
        ("weg.ref", b"NaN", False, "malformed"),
        ("weg.ref", b"[1, 2]", False, "malformed"),
        ("weg.ref", b"1" * 2000, False, "too_large"),
        ("weg.ref", b"1234", True, "retained"),
        ("weg.status", b"1", False, "not_writable"),
        ("no.such.point", b"1", False, "unknown_point"),
        ("weg.ref", b'{"value": 77, "time": 1000000000}', False, "expired"),
    ],
)
def test_bad_commands_get_a_result_and_nothing_is_sent(
    tmp_path: Path, topic: str, payload: bytes, retain: bool, error: str
) -> None:
    with rig(tmp_path) as (_b, sim, bridge, cl):
        before = ref(sim)
        writes_before = bridge.poller.summary()["slaves"][0]["requests"]
        cl.publish(f"{BASE}/{topic}/set", payload, retain=retain)
        (res,) = wait_results(cl, 1, topic)
        assert res["ok"] is False and res["error"] == error, res
        assert res["message"]
        assert ref(sim) == before
        assert bridge.commands.executed == 0
        assert bridge.poller.summary()["slaves"][0]["requests"] >= writes_before
        if retain:  # clear it, as a well-behaved client would
            cl.publish(f"{BASE}/{topic}/set", b"", retain=True)


@pytest.mark.parametrize("value", [b"1.5", b"0.5", b"2.5", b'{"value": 1000.25}'])
def test_a_value_an_integer_register_cannot_hold_is_refused_not_rounded(
    tmp_path: Path, value: bytes
) -> None:
    """weg.ref (uint16, no scale) holds whole numbers: 1.5 is refused (not written
    as 2, nor 0.5 as 0 by banker's rounding), as `Poller.write` refuses it."""
    with rig(tmp_path) as (_b, sim, bridge, cl):
        before = ref(sim)
        cl.publish(f"{BASE}/weg.ref/set", value)
        (res,) = wait_results(cl, 1)
        assert res["ok"] is False and res["error"] == "validation", res
        assert "whole number" in res["message"]
        assert ref(sim) == before and bridge.commands.executed == 0
        # a whole number written as a float is exact: taken
        cl.publish(f"{BASE}/weg.ref/set", b"2.0")
        taken = wait_results(cl, 2)[1]
        assert taken["ok"] is True and ref(sim) == 2, taken


def test_a_scaled_point_rounds_to_its_resolution_and_says_so(tmp_path: Path) -> None:
    """weg.ref_tenths (scale 0.1): 21.43 is raw 214.3, written as 214 (21.4), and
    the result says what was asked, written and the resolution; 21.4 is exact."""
    with rig(tmp_path, points=TENTHS) as (_b, sim, _bridge, cl):
        cl.publish(f"{BASE}/weg.ref_tenths/set", b'{"value": 21.43, "id": "r1"}')
        (res,) = wait_results(cl, 1, "weg.ref_tenths")
        assert res["ok"] is True and ref(sim) == 214
        assert res["rounded"] == {"requested": 21.43, "written": 21.4, "resolution": 0.1}
        cl.publish(f"{BASE}/weg.ref_tenths/set", b'{"value": 21.5, "id": "r2"}')
        res = wait_results(cl, 2, "weg.ref_tenths")[1]
        assert res["ok"] is True and "rounded" not in res and ref(sim) == 215


def test_clearing_a_retained_set_is_ignored(tmp_path: Path) -> None:
    """``mosquitto_pub -r -n``: an empty retained payload on a set topic is no
    command and gets no answer (the command after it gets the only result)."""
    with rig(tmp_path) as (_b, sim, bridge, cl):
        cl.publish(f"{BASE}/weg.ref/set", b"", retain=True)
        cl.publish(f"{BASE}/weg.status/set", b"", retain=True)  # not writable: no answer
        cl.publish(f"{BASE}/weg.ref/set", b'{"value": 321, "id": "after"}')
        (res,) = wait_results(cl, 1)
        assert res["ok"] is True and res["id"] == "after" and ref(sim) == 321
        assert results(cl, "weg.status") == []
        assert bridge.writer.stats()["ignored"] == 2


def test_an_exception_answer_is_the_result(tmp_path: Path) -> None:
    with rig(tmp_path) as (_b, _sim, _bridge, cl):
        cl.publish(f"{BASE}/weg.speed_rw/set", b"12")  # P002 is read-only: exception 3
        (res,) = wait_results(cl, 1, "weg.speed_rw")
        assert res["ok"] is False and res["error"] == "exception" and res["exception_code"] == 3


@pytest.mark.wall_clock
def test_commands_expire_in_the_queue_and_a_flood_is_bounded(tmp_path: Path) -> None:
    """write_rate 2/s: of 6 commands with an MQTT 5 expiry of 1 s, those whose turn
    comes after their expiry are answered expired and never written; with a queue of
    3, a flood of 40 is refused busy beyond it while the polls go on."""
    with rig(tmp_path, "write_rate = 2\ncommand_queue = 3") as (_b, sim, bridge, cl):
        props = Properties(PacketTypes.PUBLISH)
        props.MessageExpiryInterval = 1
        for i in range(6):
            cl.publish(f"{BASE}/weg.ref/set", b'{"value": %d}' % (100 + i), properties=props)
        res = wait_results(cl, 6)
        kinds = [r.get("error", "ok") for r in res]
        assert set(kinds) <= {"ok", "expired", "busy"}
        assert kinds.count("expired") >= 1 and kinds.count("ok") >= 1
        done = [r["value"] for r in res if r["ok"]]
        assert ref(sim) == done[-1]
        assert bridge.commands.executed == len(done)
        values_before = len(cl.on(f"{BASE}/weg.status"))
        for i in range(40):
            cl.client.publish(f"{BASE}/weg.ref/set", b"%d" % i, 1)
        res = wait_results(cl, 46)
        assert sum(r.get("error") == "busy" for r in res[6:]) >= 30
        stats = bridge.stats()["commands"]
        assert stats["busy"] >= 30
        assert stats["waiting"] <= 3
        time.sleep(0.5)
        assert bridge.stats()["buses"][0]["transactions"] > 0
        del values_before


#: an enumeration and a bit of the speed reference (P683)
TYPED = f"""
[[point]]
name = "weg.preset"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_REFERENCE}
enum = {{ 0 = "stop", 1000 = "slow", 4096 = "half" }}
writable = true
interval = 0.05
[[point]]
name = "weg.ref_bit0"
bus = "line"
slave = 1
table = "holding"
address = {weg.P_REFERENCE}
bit = 0
writable = true
interval = 0.05
"""


def test_an_enum_set_by_label_and_a_bit_written_by_read_modify_write(tmp_path: Path) -> None:
    """The CFW701 has no FC 22 (its manual's functions; the simulator answers
    exception 1): the bit is written by read-modify-write and the result says so."""
    with rig(tmp_path, points=TYPED) as (_b, sim, bridge, cl):
        cl.publish(f"{BASE}/weg.preset/set", b'"half"')
        (res,) = wait_results(cl, 1, "weg.preset")
        assert res["ok"] is True and res["value"] == "half" and "method" not in res, res
        assert ref(sim) == 4096
        cl.wait(
            lambda: any(json.loads(p)["value"] == "half" for p in cl.on(f"{BASE}/weg.preset")),
            "the label published",
        )
        before = bridge.commands.executed
        cl.publish(f"{BASE}/weg.preset/set", b'"turbo"')
        (_, refused) = wait_results(cl, 2, "weg.preset")
        assert refused["ok"] is False and refused["error"] == "validation", refused
        assert "'stop', 'slow', 'half'" in refused["message"]
        assert ref(sim) == 4096 and bridge.commands.executed == before
        # bit 0 of the same register, the others kept
        cl.publish(f"{BASE}/weg.ref_bit0/set", b"true")
        (bit,) = wait_results(cl, 1, "weg.ref_bit0")
        assert bit["ok"] is True and bit["value"] is True, bit
        assert bit["method"] == "read_modify_write"
        assert ref(sim) == 4097
        # 4097 has no label: the number itself is published
        cl.wait(
            lambda: json.loads(cl.on(f"{BASE}/weg.preset")[-1])["value"] == 4097,
            "an unlabelled value as the number",
        )
