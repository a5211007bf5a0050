"""The register types end to end in the poller: a pyrtu slave on the virtual bus
(no FC 22: bits written by read-modify-write) and libmodbus over TCP (FC 22, unit
ids 255 and 0).  A device's "no value" marker is quality bad, never the number;
an enum is its label both ways; a bit write keeps the register's other bits."""

from __future__ import annotations

import asyncio
import math
import struct
from collections.abc import Callable

import pytest
from peers import pattern
from waiting import wait_for

from pyrtu.drivers.slave import Slave
from pyrtu.drivers.slave_base import STANDARD_FUNCTIONS
from pyrtu.poller import Bus, Point, Poller, Update, make_config, parse_config
from pyrtu.protocol.datastore import DataStore

pytest_plugins = ["peers.fixtures"]
vbus = pytest.importorskip("pyrtu.vbus")

BAUD = 115200
PATIENCE = 30.0


async def until(condition: Callable[[], bool], what: str) -> None:
    await wait_for(condition, what, PATIENCE)


def regs(fmt: str, value: object, swap_words: bool = False) -> list[int]:
    """``value`` packed big-endian by struct, as registers (words reversed: CDAB)."""
    raw = struct.pack(">" + fmt, value)
    words = [raw[i] << 8 | raw[i + 1] for i in range(0, len(raw), 2)]
    return words[::-1] if swap_words else words


def store() -> DataStore:
    s = DataStore()
    s.holding_registers.add_range(
        0,
        [
            0xFFFF,  # 0: uint16, error_value 0xFFFF
            *regs("f", math.nan),  # 1-2: float32, error_value nan
            0x8000,  # 3: int16, unsupported_value 0x8000 (its register pattern)
            2,  # 4: enum: cool
            0b1010_0000,  # 5: an alarm word: bit 5 set, bits 4..7 = 0xA
            *regs("q", -5, swap_words=True),  # 6-9: int64, word swap
            0x1234,  # 10: bits written one by one
            0x12A4,  # 11: bcd16 with a digit above 9: no number
            *regs("e", 2.0**-24),  # 12: float16, the smallest subnormal
        ],
    )
    return s


def points() -> list[Point]:
    kw: dict[str, object] = dict(bus="line", slave=1, table="holding", interval=0.05)
    return [
        Point("marker16", address=0, error_value=0xFFFF, **kw),  # type: ignore[arg-type]
        Point("nanfloat", address=1, type="float32", error_value=math.nan, **kw),  # type: ignore[arg-type]
        Point("pattern16", address=3, type="int16", unsupported_value=0x8000, **kw),  # type: ignore[arg-type]
        Point("mode", address=4, enum={"0": "off", "1": "heat", "2": "cool"}, writable=True, **kw),  # type: ignore[arg-type]
        Point("alarm5", address=5, bit=5, **kw),  # type: ignore[arg-type]
        Point("field", address=5, bits=[4, 4], **kw),  # type: ignore[arg-type]
        Point("energy", address=6, type="int64", order="CDAB", **kw),  # type: ignore[arg-type]
        Point("flag3", address=10, bit=3, writable=True, **kw),  # type: ignore[arg-type]
        Point("nibble", address=10, bits=[8, 4], writable=True, **kw),  # type: ignore[arg-type]
        Point("badbcd", address=11, type="bcd16", **kw),  # type: ignore[arg-type]
        Point("half", address=12, type="float16", **kw),  # type: ignore[arg-type]
    ]


def test_markers_enums_bits_and_read_modify_write_on_the_virtual_bus() -> None:
    async def main(data: DataStore) -> tuple[dict[str, Update], list[str], dict[str, Update]]:
        with vbus.VirtualBus(2, baudrate=BAUD, parity="N") as line:
            no_fc22 = set(STANDARD_FUNCTIONS) - {22}  # answers FC 22 with exception 1
            slave = Slave(
                line.paths[1], address=1, store=data, baudrate=BAUD, parity="N", functions=no_fc22
            )
            slave.start()
            try:
                bus = Bus("line", line.paths[0], {"baudrate": BAUD, "parity": "N", "timeout": 0.2})
                poller = Poller(make_config([bus], points()))
                seen: dict[str, Update] = {}
                poller.on_update(lambda u: seen.__setitem__(u.point.name, u))
                async with poller:
                    await until(lambda: len(seen) == len(points()), "every point")
                    first = dict(seen)
                    hows = [await poller.write("mode", "heat")]
                    with pytest.raises(ValueError, match="'off', 'heat', 'cool'"):
                        await poller.write("mode", "auto")
                    hows.append(await poller.write("flag3", False))  # 0x1234: bit 3 was set
                    hows.append(await poller.write("nibble", 0xB))
                    data.holding_registers.set(0, 42)
                    await until(lambda: seen["marker16"].value == 42, "a value again")
                    await until(lambda: seen["mode"].value == "heat", "the label read")
                    return first, hows, dict(seen)
            finally:
                slave.stop()

    data = store()
    first, hows, later = asyncio.run(main(data))
    for name in ("marker16", "nanfloat", "pattern16", "badbcd"):
        assert first[name].value is None and first[name].quality == "bad", name
        assert first[name].as_dict()["quality"] == "bad"
    assert first["mode"].value == "cool"
    assert first["alarm5"].value is True and first["field"].value == 0xA
    assert first["energy"].value == -5
    assert first["half"].value == 2.0**-24
    assert later["marker16"].value == 42 and later["marker16"].quality == "good"
    # a pyrtu slave has no FC 22: exception 1, then read-modify-write, remembered
    assert hows == ["write", "read_modify_write", "read_modify_write"]
    assert data.holding_registers.get(4) == 1  # "heat"
    assert data.holding_registers.get(10) == 0x1B34  # bit 3 cleared, bits 8..11 = 0xB


def test_tcp_units_255_and_0_and_fc22(libmodbus_tcp: str) -> None:
    text = f"""
[[bus]]
name = "plc"
port = "{libmodbus_tcp}"
timeout = 1

[[point]]
name = "at255"
bus = "plc"
slave = 255
table = "holding"
address = 7
interval = 0.05

[[point]]
name = "at0"
bus = "plc"
slave = 0
table = "holding"
address = 8
interval = 0.05

[[point]]
name = "bit0"
bus = "plc"
slave = 255
table = "holding"
address = 20
bit = 0
writable = true
interval = 0.05
"""
    cfg = parse_config(text, "plc.toml")

    async def main() -> tuple[dict[str, object], str, list[int] | list[bool]]:
        poller = Poller(cfg)
        seen: dict[str, object] = {}
        poller.on_update(lambda u: seen.__setitem__(u.point.name, u.value))
        async with poller:
            await until(lambda: len(seen) == 3, "every point")
            value = pattern.holding(1, 20)
            how = await poller.write("bit0", not value & 1)
            after = await poller.read_registers("plc", 255, "holding", 20, 1)
            return dict(seen), how, after

    seen, how, after = asyncio.run(main())
    # libmodbus answers every unit id with slave 1's pattern
    assert seen["at255"] == pattern.holding(1, 7) and seen["at0"] == pattern.holding(1, 8)
    assert how == "mask_write"
    assert after == [pattern.holding(1, 20) ^ 1]  # bit 0 flipped, the others kept


def test_unit_ids_beyond_247_are_for_tcp_buses_only() -> None:
    serial = '[[bus]]\nname = "l"\nport = "/dev/ttyX"\n'
    point = '[[point]]\nname = "p"\nbus = "l"\nslave = 255\ntable = "holding"\naddress = 0\n'
    with pytest.raises(
        ValueError, match=r"c.toml:7: point\[0\] \(\"p\"\): slave: must be an integer 1\.\.247"
    ):
        parse_config(serial + point, "c.toml")
    with pytest.raises(ValueError, match=r"slave: must be an integer 1\.\.247"):
        parse_config(serial + point.replace("255", "0"), "c.toml")
    tcp = '[[bus]]\nname = "l"\nport = "tcp://127.0.0.1:1502"\n'
    assert parse_config(tcp + point, "c.toml").points[0].slave == 255
    assert parse_config(tcp + point.replace("255", "0"), "c.toml").points[0].slave == 0
    with pytest.raises(
        ValueError,
        match=r"c.toml:7: .*slave: must be an integer 0\.\.255 on a Modbus TCP bus, not 256",
    ):
        parse_config(tcp + point.replace("255", "256"), "c.toml")
    device = '[[device]]\nbus = "l"\nslave = 255\n'
    assert parse_config(tcp + device + point, "c.toml").devices[0].slave == 255
    with pytest.raises(ValueError, match=r"device\[0\]: slave: must be an integer 1\.\.247"):
        parse_config(serial + device + point, "c.toml")


BUS = '[[bus]]\nname = "l"\nport = "/dev/ttyX"\n'


def point_table(name: str, address: int, extra: str) -> str:
    return (
        f'\n[[point]]\nname = "{name}"\nbus = "l"\nslave = 1\ntable = "holding"\n'
        f"address = {address}\n{extra}\n"
    )


@pytest.mark.parametrize(
    ("tables", "where"),
    [
        # overlapping points of different types: the second, at its address
        (point_table("a", 10, 'type = "float32"') + point_table("b", 11, ""),
         'c.toml:18: point[1] ("b"): address: registers 11..11 (uint16 AB) overlap point'
         " 'a''s 10..11 (float32 ABCD)"),
        (point_table("a", 10, 'type = "uint32"') + point_table("b", 10, 'type = "float32"'),
         'c.toml:18: point[1] ("b"): address: registers 10..11 (float32 ABCD) overlap'),
        (point_table("a", 65533, 'type = "uint64"'),
         'c.toml:10: point[0] ("a"): address: 65533 + 4 registers runs past 65535'),
        (point_table("a", 0, "bit = 16"), 'c.toml:11: point[0] ("a"): bit: must be 0..15, not 16'),
        (point_table("a", 0, "bits = [12, 5]"), 'c.toml:11: point[0] ("a"): bits: must be 1..4'),
        (point_table("a", 0, 'type = "float32"\nbit = 1'),
         'c.toml:11: point[0] ("a"): type: a bit is a bool'),
        (point_table("a", 0, 'enum = { 0 = "off", 70000 = "x" }'),
         'c.toml:11: point[0] ("a"): enum: value 70000 is outside the point\'s 0..65535'),
        (point_table("a", 0, "min = 5\nmax = 1"),
         'c.toml:12: point[0] ("a"): max: must be at least min (5), not 1'),
        (point_table("a", 0, 'type = "int16"\nerror_value = 0x18000'),
         'c.toml:12: point[0] ("a"): error_value: must be -32768..32767'),
        (point_table("a", 0, 'type = "uint64"\norder = "ABDC"'),
         'c.toml:12: point[0] ("a"): order: a uint64 takes ABCDEFGH, GHEFCDAB, BADCFEHG,'
         " HGFEDCBA (or the 32-bit names ABCD, CDAB, BADC, DCBA), not 'ABDC'"),
        (point_table("a", 0, "writable = true\nsclae = 2"),
         'c.toml:12: point[0] ("a"): sclae: unknown key (known: name, bus'),
        (point_table("a", 0, 'device_class = 3'),
         'c.toml:11: point[0] ("a"): device_class: must be a string, not 3'),
    ],
)  # fmt: skip
def test_bad_points_name_file_line_point_and_key(tables: str, where: str) -> None:
    with pytest.raises(ValueError) as e:
        parse_config(BUS + tables, "c.toml")
    assert where in str(e.value), str(e.value)


def test_views_of_one_register_may_overlap() -> None:
    tables = (
        point_table("word", 5, "")
        + point_table("hi", 5, 'type = "uint8"\norder = "high"')
        + point_table("lo", 5, 'type = "int8"\norder = "low"')
        + point_table("b3", 5, "bit = 3")
        + point_table("f", 5, "bits = [4, 4]")
        + point_table("twice", 6, 'type = "float32"')
        + point_table("again", 6, 'type = "float32"')
    )
    assert len(parse_config(BUS + tables, "c.toml").points) == 7
    last = point_table("end", 65532, 'type = "uint64"')  # 65532..65535: the last fits
    assert parse_config(BUS + last, "c.toml").points[0].end == 0x10000


def test_writes_refused_before_a_byte_is_sent() -> None:
    from pyrtu.poller.points import encode_point_value

    kw: dict[str, object] = dict(bus="l", slave=1, table="holding", address=0)
    ranged = Point("r", scale=0.1, min=0, max=50, **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"'r': 50.1 is outside its min..max \(0..50\)"):
        encode_point_value(ranged, 50.1)
    assert encode_point_value(ranged, 50).words == [500]
    text = Point("t", type="string", count=2, **kw)  # type: ignore[arg-type]
    with pytest.raises(
        ValueError, match="'t': 'abcde' is 5 characters; its registers hold at most 4"
    ):
        encode_point_value(text, "abcde")
    mode = Point("m", enum=["off", "heat"], **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"'m': 'cool' is not one of its labels \('off', 'heat'\)"):
        encode_point_value(mode, "cool")
    assert encode_point_value(mode, "heat").words == [1]
    assert encode_point_value(mode, 0).value == "off"
    field = Point("f", bits=[4, 3], **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"outside 0\.\.7"):
        encode_point_value(field, 8)
    assert encode_point_value(field, 5).mask == (0xFF8F, 0x0050)
    swapped = Point("s", bit=0, order="BA", **kw)  # type: ignore[arg-type]
    assert encode_point_value(swapped, True).mask == (0xFEFF, 0x0100)  # bit 0 in the 2nd byte
    with pytest.raises(ValueError, match="read only"):
        encode_point_value(Point("i", bus="l", slave=1, table="input", address=0, bit=1), True)


def test_published_values_are_the_shortest_faithful_decimals() -> None:
    from pyrtu.poller.values import faithful_value

    kw: dict[str, object] = dict(bus="l", slave=1, table="holding", address=0)
    half = Point("h", type="float16", **kw)  # type: ignore[arg-type]
    tenth = struct.unpack(">e", struct.pack(">e", 0.1))[0]  # 0.0999755859375
    assert half.decode([struct.unpack(">H", struct.pack(">e", 0.1))[0]], 0) == tenth
    assert faithful_value(half, tenth) == 0.1
    energy = Point("e", type="int64", scale=0.1, **kw)  # type: ignore[arg-type]
    assert faithful_value(energy, energy.decode([0, 0, 0, 3], 0)) == 0.3  # not 0.30000000000000004
    byte = Point("b", type="uint8", order="low", scale=0.5, offset=0.1, **kw)  # type: ignore[arg-type]
    assert faithful_value(byte, byte.decode([0x0003], 0)) == 1.6
    door = Point("d", bit=2, enum=["closed", "open"], **kw)  # type: ignore[arg-type]
    assert door.decode([0b100], 0) == "open" and door.decode([0b011], 0) == "closed"
