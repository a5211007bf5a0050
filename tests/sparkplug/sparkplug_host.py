"""A Sparkplug B host application for the tests, written from the specification
(Eclipse Sparkplug 3.0.0, chapter 6, the payload's field numbers and types) and
the protobuf wire format, with no code of pyrtu and no protobuf library: what
the edge node publishes is decoded here by a decoder of its own.

`Host` subscribes to ``spBv1.0/#`` on a broker, keeps every message (topic, QoS,
retain flag, decoded payload) and publishes the host's STATE and commands.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

# -------------------------------------------------------------- the wire format


def _varint(data: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = data[i]
        i += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, i
        shift += 7


def fields(data: bytes) -> list[tuple[int, int, Any]]:
    """(field number, wire type, raw value) of every field of a message."""
    out = []
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        num, wire = key >> 3, key & 7
        if wire == 0:
            v, i = _varint(data, i)
        elif wire == 1:
            v = data[i : i + 8]
            i += 8
        elif wire == 2:
            n, i = _varint(data, i)
            v = data[i : i + n]
            i += n
        elif wire == 5:
            v = data[i : i + 4]
            i += 4
        else:
            raise ValueError(f"wire type {wire}")
        out.append((num, wire, v))
    return out


def _enc_varint(v: int) -> bytes:
    out = bytearray()
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def enc_field(num: int, wire: int, value: Any) -> bytes:
    key = _enc_varint(num << 3 | wire)
    if wire == 0:
        return key + _enc_varint(value)
    if wire == 2:
        return key + _enc_varint(len(value)) + value
    if wire == 5:
        return key + value
    return key + value  # wire 1: 8 bytes given


# -------------------------------------------------------------- Sparkplug B

#: Payload.Metric's value fields (number -> name), chapter 6
VALUE_FIELDS = {10: "int_value", 11: "long_value", 12: "float_value", 13: "double_value",
                14: "boolean_value", 15: "string_value", 16: "bytes_value"}  # fmt: skip
#: DataType numbers, chapter 6 "Data Types"
DT = {"Int8": 1, "Int16": 2, "Int32": 3, "Int64": 4, "UInt8": 5, "UInt16": 6, "UInt32": 7,
      "UInt64": 8, "Float": 9, "Double": 10, "Boolean": 11, "String": 12}  # fmt: skip


@dataclass
class Metric:
    name: str | None = None
    alias: int | None = None
    timestamp: int | None = None
    datatype: int | None = None
    is_historical: bool = False
    is_null: bool = False
    value_field: str | None = None
    raw: Any = None
    properties: dict[str, tuple[int, Any]] = field(default_factory=dict)

    def value(self, datatype: int) -> Any:
        """The value as the datatype says (two's complement for signed integers)."""
        if self.is_null:
            return None
        r = self.raw
        if datatype in (1, 2, 3):  # int_value: 32-bit two's complement
            return r - (1 << 32) if r >= 1 << 31 else r
        if datatype == 4:  # long_value: 64-bit two's complement
            return r - (1 << 64) if r >= 1 << 63 else r
        return r


def _value(num: int, wire: int, raw: Any) -> Any:
    name = VALUE_FIELDS[num]
    if name == "float_value":
        return struct.unpack("<f", raw)[0]
    if name == "double_value":
        return struct.unpack("<d", raw)[0]
    if name == "boolean_value":
        return bool(raw)
    if name == "string_value":
        return raw.decode("utf-8")
    return raw


def _property_set(data: bytes) -> dict[str, tuple[int, Any]]:
    keys: list[str] = []
    values: list[tuple[int, Any]] = []
    for num, _w, raw in fields(data):
        if num == 1:
            keys.append(raw.decode())
        elif num == 2:
            t, v = 0, None
            for n2, _wire2, r2 in fields(raw):
                if n2 == 1:
                    t = r2
                elif n2 == 3:
                    v = r2
                elif n2 == 6:
                    v = struct.unpack("<d", r2)[0]
                elif n2 == 7:
                    v = bool(r2)
                elif n2 == 8:
                    v = r2.decode()
            values.append((t, v))
    assert len(keys) == len(values), "tck-id-payloads-propertyset-values-array-size"
    return dict(zip(keys, values, strict=True))


def _metric(data: bytes) -> Metric:
    m = Metric()
    for num, wire, raw in fields(data):
        if num == 1:
            m.name = raw.decode("utf-8")
        elif num == 2:
            m.alias = raw
        elif num == 3:
            m.timestamp = raw
        elif num == 4:
            m.datatype = raw
        elif num == 5:
            m.is_historical = bool(raw)
        elif num == 7:
            m.is_null = bool(raw)
        elif num == 9:
            m.properties = _property_set(raw)
        elif num in VALUE_FIELDS:
            assert m.value_field is None, "two value fields in one metric (a oneof)"
            m.value_field = VALUE_FIELDS[num]
            m.raw = _value(num, wire, raw)
    return m


@dataclass
class Payload:
    timestamp: int | None = None
    seq: int | None = None
    metrics: list[Metric] = field(default_factory=list)


def decode(data: bytes) -> Payload:
    p = Payload()
    for num, _wire, raw in fields(data):
        if num == 1:
            p.timestamp = raw
        elif num == 2:
            p.metrics.append(_metric(raw))
        elif num == 3:
            p.seq = raw
    return p


def encode_metric(
    *, name: str | None = None, alias: int | None = None, datatype: int | None = None,
    value_field: str = "boolean_value", value: Any = True,
) -> bytes:  # fmt: skip
    """A command's metric, encoded by hand."""
    out = b""
    if name is not None:
        out += enc_field(1, 2, name.encode())
    if alias is not None:
        out += enc_field(2, 0, alias)
    out += enc_field(3, 0, int(time.time() * 1000))
    if datatype is not None:
        out += enc_field(4, 0, datatype)
    num = {v: k for k, v in VALUE_FIELDS.items()}[value_field]
    if value_field == "float_value":
        out += enc_field(num, 5, struct.pack("<f", value))
    elif value_field == "double_value":
        out += enc_field(num, 1, struct.pack("<d", value))
    elif value_field == "string_value":
        out += enc_field(num, 2, value.encode())
    elif value_field == "boolean_value":
        out += enc_field(num, 0, int(bool(value)))
    else:
        out += enc_field(num, 0, value)
    return out


def encode_payload(*metrics: bytes) -> bytes:
    """A command's payload (NCMD, DCMD: a timestamp, metrics, no seq)."""
    out = enc_field(1, 0, int(time.time() * 1000))
    for m in metrics:
        out += enc_field(2, 2, m)
    return out


# -------------------------------------------------------------- the host


@dataclass
class Message:
    topic: str
    qos: int
    retain: bool
    payload: bytes
    arrived: float

    @property
    def kind(self) -> str:
        return self.topic.split("/")[2]

    @property
    def device(self) -> str | None:
        parts = self.topic.split("/")
        return parts[4] if len(parts) > 4 else None

    def decoded(self) -> Payload:
        return decode(self.payload)


class Host:
    """A host application on ``broker`` (tests/mqtt_broker.py's `Broker`)."""

    def __init__(self, broker: Any, host_id: str = "scada") -> None:
        self.host_id = host_id
        self.messages: list[Message] = []
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self.subscriptions = 0  # one more after each (re)connection
        c = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"host-{host_id}-{time.time_ns()}",
                        protocol=mqtt.MQTTv311, clean_session=True)  # fmt: skip
        self.client = c

        def on_connect(*args: object) -> None:
            c.subscribe("spBv1.0/#", qos=1)

        def on_subscribe(*args: object) -> None:
            self.subscriptions += 1
            self._subscribed.set()

        def on_message(client: object, userdata: object, msg: mqtt.MQTTMessage) -> None:
            with self._lock:
                self.messages.append(Message(msg.topic, msg.qos, bool(msg.retain),
                                             bytes(msg.payload), time.monotonic()))  # fmt: skip

        c.on_connect = on_connect
        c.on_subscribe = on_subscribe
        c.on_message = on_message
        c.connect("127.0.0.1", broker.port)
        c.loop_start()
        if not self._subscribed.wait(10):
            raise TimeoutError("the host did not subscribe")

    def state(self, online: bool, timestamp: int | None = None) -> int:
        """Publish the host's STATE (retained, QoS 1, as a host does); its timestamp."""
        ts = int(time.time() * 1000) if timestamp is None else timestamp
        body = json.dumps({"online": online, "timestamp": ts}).encode()
        self.client.publish(
            f"spBv1.0/STATE/{self.host_id}", body, qos=1, retain=True
        ).wait_for_publish(10)
        return ts

    def command(self, topic: str, payload: bytes) -> None:
        self.client.publish(topic, payload, qos=0, retain=False).wait_for_publish(10)

    def of(self, kind: str, device: str | None = None) -> list[Message]:
        with self._lock:
            return [
                m
                for m in self.messages
                if m.kind == kind and (device is None or m.device == device)
            ]

    def snapshot(self) -> list[Message]:
        with self._lock:
            return [m for m in self.messages if m.kind != "STATE"]

    def wait(self, condition: Any, what: str, patience: float = 30.0) -> None:
        """Until ``condition()`` holds (a safety net of ``patience`` s, not a measure)."""
        give_up = time.monotonic() + patience
        while not condition():
            assert time.monotonic() < give_up, f"gave up waiting for {what}"
            time.sleep(0.02)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


__all__ = [
    "DT",
    "Host",
    "Message",
    "Metric",
    "Payload",
    "decode",
    "encode_metric",
    "encode_payload",
]
