"""pyrtu.core._crcfast: the C core's CRC-16/MODBUS as CPython builtins (issue 20).

csrc/python/rtu_crc_py.c must give what the cffi functions of the C backend and the
pure-Python twin give -- the same CRC (Modbus over Serial Line V1.02, 6.2.2: 0xA001
reflected, preset 0xFFFF, appended low byte first) for every buffer, and the same
exceptions with the same messages for everything else -- and the package must use it
where the C backend runs, and never with PYRTU_PURE=1.
"""

from __future__ import annotations

import array
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from c_core import missing, need_c
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from vectors import crc_bitwise

import pyrtu
from pyrtu.core import crcshapes as _crcshapes
from pyrtu.core._pure import crc as twin

ROOT = Path(__file__).resolve().parents[2]


def _cext() -> ModuleType:
    need_c()
    from pyrtu.core import _cext

    return _cext


def _fast() -> ModuleType:
    """pyrtu.core._crcfast; a build that has the C core but not it fails with PYRTU_REQUIRE_C=1."""
    _cext()
    try:
        from pyrtu.core import _crcfast
    except ImportError as exc:
        missing(f"pyrtu.core._crcfast is not built here ({exc})")
    return _crcfast


# each function, as (builtin, cffi function of the C backend, twin function) names
CRC16 = ("crc16", "_cffi_crc16", "crc16")
ADD = ("add_crc", "_cffi_add_crc", "add_crc")
CHECK = ("check_crc", "_cffi_check_crc", "check_crc")


def _three(names: tuple[str, str, str]) -> list[Callable[..., Any]]:
    fast, cext = _fast(), _cext()
    return [getattr(fast, names[0]), getattr(cext, names[1]), getattr(twin, names[2])]


def _shapes() -> list[tuple[Callable[..., Any], Callable[..., Any], Callable[..., Any]]]:
    """(builtin, cffi-based, twin-based) for crc16_bytes and crc16_swapped."""
    fast, cext = _fast(), _cext()
    cffi_bytes = _crcshapes._crc16_bytes  # the Python shapes over the active crc16

    def twin_bytes(data: Any) -> bytes:
        return bytes(twin.crc16(data).to_bytes(2, "little"))

    def twin_swapped(data: Any) -> int:
        crc = twin.crc16(data)
        return ((crc & 0xFF) << 8) | (crc >> 8)

    def cffi_swapped(data: Any) -> int:
        crc = cext._cffi_crc16(data)
        return ((crc & 0xFF) << 8) | (crc >> 8)

    return [
        (fast.crc16_bytes, cffi_bytes, twin_bytes),
        (fast.crc16_swapped, cffi_swapped, twin_swapped),
    ]


AGREE = settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


# ---------------------------------------------------------------------------
# the same results
# ---------------------------------------------------------------------------
def test_check_value_and_a_known_frame() -> None:
    fast = _fast()
    assert fast.crc16(b"123456789") == 0x4B37
    # FC 03, slave 1, 10 registers from 0: CRC 0xCDC5, on the wire C5 CD (6.2.2)
    pdu = bytes.fromhex("01030000000a")
    assert fast.crc16(pdu) == 0xCDC5
    assert fast.crc16_bytes(pdu) == b"\xc5\xcd"
    assert fast.crc16_swapped(pdu) == 0xC5CD
    assert fast.add_crc(pdu) == pdu + b"\xc5\xcd"
    assert fast.check_crc(pdu + b"\xc5\xcd")
    assert not fast.check_crc(pdu + b"\xcd\xc5")


@AGREE
@given(data=st.binary(min_size=0, max_size=600), seed=st.integers(0, 0xFFFF))
def test_crc16_agrees_with_cffi_and_twin(data: bytes, seed: int) -> None:
    fast, cffi, py = _three(CRC16)
    want = crc_bitwise(data, seed)
    assert fast(data, seed) == cffi(data, seed) == py(data, seed) == want
    assert fast(data, crc=seed) == want
    assert fast(data) == cffi(data) == py(data) == crc_bitwise(data)


@AGREE
@given(data=st.binary(min_size=0, max_size=600))
def test_shapes_add_and_check_agree(data: bytes) -> None:
    for fast, cffi, py in _shapes():
        assert fast(data) == cffi(data) == py(data), fast
    fast_add, cffi_add, py_add = _three(ADD)
    adu = fast_add(data)
    assert type(adu) is bytes
    assert adu == cffi_add(data) == py_add(data)
    fast_check, cffi_check, py_check = _three(CHECK)
    for candidate in (data, adu, adu[:-1] + bytes((adu[-1] ^ 0x80,))):
        assert fast_check(candidate) is cffi_check(candidate) is py_check(candidate)
    assert fast_check(adu) is (len(adu) >= 3)


def test_empty_input() -> None:
    fast = _fast()
    for empty in (b"", bytearray(), memoryview(b""), array.array("B")):
        assert fast.crc16(empty) == 0xFFFF
        assert fast.crc16(empty, 0x1234) == 0x1234
        assert fast.crc16_bytes(empty) == b"\xff\xff"
        assert fast.crc16_swapped(empty) == 0xFFFF
        assert fast.add_crc(empty) == b"\xff\xff"
        assert fast.check_crc(empty) is False


def _buffers(raw: bytes) -> list[Any]:
    """Contiguous buffers holding ``raw`` (its bytes in order)."""
    return [
        bytearray(raw),
        memoryview(raw),
        memoryview(bytearray(b"\0" + raw))[1:],  # an odd start address
        array.array("B", raw),
        array.array("H", raw[: len(raw) & ~1]),
        memoryview(raw[: len(raw) & ~3]).cast("I"),
        memoryview(raw[:240]).cast("B", (12, 20)),  # 2-D, C-contiguous
        type("Sub", (bytes,), {})(raw),  # a bytes subclass: the buffer path
    ]


def _strided(raw: bytes) -> list[Any]:
    """Non-contiguous buffers: their bytes in logical order are what they hold."""
    return [
        memoryview(raw)[::2],
        memoryview(raw)[::-1],
        memoryview(bytearray(raw))[1::3],
        memoryview(array.array("H", raw[: len(raw) & ~1]))[::2],
        memoryview(raw[:240]).cast("B", (12, 20))[::2],
    ]


@pytest.mark.parametrize("kind", ["contiguous", "strided"])
def test_every_buffer_like_the_twin(kind: str) -> None:
    """Each buffer gives the CRC of its bytes in logical order (memoryview.tobytes()), on
    every implementation: a strided one is read through a copy, not refused."""
    raw = bytes(range(256)) * 2
    objs = _buffers(raw) if kind == "contiguous" else _strided(raw)
    crc16s, adds, checks = _three(CRC16), _three(ADD), _three(CHECK)
    for obj in objs:
        logical = memoryview(obj).tobytes()
        want = crc_bitwise(logical)
        assert [f(obj) for f in crc16s] == [want] * 3, obj
        assert [f(obj, 0x55AA) for f in crc16s] == [crc_bitwise(logical, 0x55AA)] * 3, obj
        assert [f(obj) for f in adds] == [logical + want.to_bytes(2, "little")] * 3, obj
        assert len({f(obj) for f in checks}) == 1, obj
        for fast, cffi, py in _shapes():
            assert fast(obj) == cffi(obj) == py(obj), (fast, obj)
    adu = pyrtu.backend("python").add_crc(raw[:100])
    strided_adu = memoryview(bytes(x for b in adu for x in (b, 0)))[::2]
    assert [f(strided_adu) for f in checks] == [True] * 3


def test_large_input_runs_without_the_gil_and_agrees() -> None:
    """From 64 KiB the CRC runs with the GIL released (csrc/python/rtu_crc_py.c)."""
    import random

    fast, cffi, py = _three(CRC16)
    fast_add = _fast().add_crc
    data = bytearray(random.Random(20).randbytes(200_000))
    want = crc_bitwise(bytes(data))
    assert fast(data) == cffi(data) == py(data) == want
    assert fast(memoryview(data)[::2]) == py(memoryview(data)[::2])
    # incremental across the threshold: 1000 bytes with the GIL, the rest without
    assert fast(memoryview(data)[1000:], fast(bytes(data[:1000]))) == want
    assert fast_add(data) == bytes(data) + want.to_bytes(2, "little")


def test_buffers_are_released() -> None:
    """A bytearray whose buffer is still exported cannot be resized: after each call,
    with a good or a bad seed, it can."""
    fast = _fast()
    data = bytearray(b"\x01\x03\x00\x00\x00\x0a")
    calls: list[Callable[[], object]] = [
        lambda: fast.crc16(data),
        lambda: fast.crc16(data, 0x1234),
        lambda: fast.crc16_bytes(data),
        lambda: fast.crc16_swapped(data),
        lambda: fast.add_crc(data),
        lambda: fast.check_crc(data),
        lambda: fast.crc16(memoryview(data)[::2]),
    ]
    for call in calls:
        call()
        data.append(0)  # BufferError if the buffer were still held
        del data[-1]
    for bad in (-1, 0x10000, 1.5, True, None):
        with pytest.raises((TypeError, ValueError)):
            fast.crc16(data, bad)
        data.append(0)
        del data[-1]


# ---------------------------------------------------------------------------
# the same errors
# ---------------------------------------------------------------------------
class _NotABuffer:
    pass


BAD_DATA: list[Any] = ["text", None, 5, 1.0, [1, 2, 3], _NotABuffer(), {b"x"}]
BAD_SEEDS: list[Any] = [-1, 0x10000, 2**70, -(2**70), True, False, 1.5, "1", None, b"\x01"]


def _outcome(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[str, str]:
    try:
        result = fn(*args, **kwargs)
    except Exception as exc:
        return type(exc).__name__, str(exc)
    return "ok", repr(result)


@pytest.mark.parametrize("bad", BAD_DATA, ids=lambda b: type(b).__name__)
def test_wrong_data_types_raise_the_same_typeerror(bad: Any) -> None:
    for names, argname in ((CRC16, "data"), (ADD, "data"), (CHECK, "adu")):
        outcomes = {_outcome(f, bad) for f in _three(names)}
        assert outcomes == {
            ("TypeError", f"{argname} must be a bytes-like object, not {type(bad).__name__}")
        }, (names, outcomes)
    for shape in _shapes():
        outcomes = {_outcome(f, bad) for f in shape}
        assert outcomes == {
            ("TypeError", f"data must be a bytes-like object, not {type(bad).__name__}")
        }, (shape, outcomes)


@pytest.mark.parametrize("seed", BAD_SEEDS, ids=repr)
def test_bad_seeds_raise_the_same_error(seed: Any) -> None:
    outcomes = {_outcome(f, b"\x01\x03", seed) for f in _three(CRC16)}
    if isinstance(seed, int) and not isinstance(seed, bool):
        want = ("ValueError", f"crc must be an integer 0..0xFFFF, not {seed!r}")
    else:
        want = ("TypeError", f"crc must be an integer 0..0xFFFF, not {type(seed).__name__}")
    assert outcomes == {want}
    # the data is checked first, on every implementation
    outcomes = {_outcome(f, "text", seed) for f in _three(CRC16)}
    assert outcomes == {("TypeError", "data must be a bytes-like object, not str")}


def test_int_subclass_seed_and_bounds() -> None:
    class Seed(int):
        pass

    for seed in (0, 0xFFFF, Seed(0x1234)):
        outcomes = {_outcome(f, b"abc", seed) for f in _three(CRC16)}
        assert outcomes == {("ok", repr(crc_bitwise(b"abc", int(seed))))}


@pytest.mark.parametrize(
    ("args", "kwargs"),
    [
        ((), {}),
        ((b"x", 1, 2), {}),
        ((), {"data": b"x"}),
        ((), {"data": b"x", "crc": 7}),
        ((b"x",), {"crc": 7}),
        ((b"x",), {"data": b"y"}),
        ((b"x",), {"seed": 7}),
        ((b"x", 7), {"crc": 7}),
    ],
)
def test_crc16_arguments_bind_like_the_twin(args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
    fast, _, py = _three(CRC16)
    assert _outcome(fast, *args, **kwargs) == _outcome(py, *args, **kwargs)


@pytest.mark.parametrize(
    ("args", "kwargs"),
    [((), {}), ((b"x", b"y"), {}), ((), {"data": b"x"}), ((b"x",), {"adu": b"x"})],
)
def test_one_argument_functions_bind_like_the_twin(
    args: tuple[Any, ...], kwargs: dict[str, Any]
) -> None:
    fast = _fast()
    for name in ("add_crc", "check_crc"):
        want = _outcome(getattr(twin, name), *args, **kwargs)
        assert _outcome(getattr(fast, name), *args, **kwargs) == want, name
    # the shapes: crc16_bytes(data) / crc16_swapped(data) as in pyrtu.core.crcshapes
    for fast_fn, py_fn in (
        (fast.crc16_bytes, _crcshapes._crc16_bytes),
        (fast.crc16_swapped, _crcshapes._crc16_swapped),
    ):
        got, want = _outcome(fast_fn, *args, **kwargs), _outcome(py_fn, *args, **kwargs)
        assert got[0] == want[0], (fast_fn, got, want)
        assert got[1] == want[1].replace("_crc16_", "crc16_"), (fast_fn, got, want)


# ---------------------------------------------------------------------------
# where it is used
# ---------------------------------------------------------------------------
def test_the_c_backend_and_the_shapes_use_it() -> None:
    fast, cext = _fast(), _cext()
    if os.environ.get("PYRTU_PURE") == "1":  # the twin runs: the C backend keeps cffi
        assert cext.CRCFAST is None
        assert cext.crc16 is cext._cffi_crc16
        assert pyrtu.crc16 is twin.crc16
        return
    assert cext.CRCFAST is fast
    assert (cext.crc16, cext.add_crc, cext.check_crc) == (fast.crc16, fast.add_crc, fast.check_crc)
    if pyrtu.BACKEND == "c":
        assert pyrtu.crc16 is fast.crc16
        assert pyrtu.add_crc is fast.add_crc
        assert pyrtu.check_crc is fast.check_crc
        assert pyrtu.crc16_bytes is fast.crc16_bytes
        assert pyrtu.crc16_swapped is fast.crc16_swapped
        crc = pyrtu.Crc16(b"1234")
        crc.update(bytearray(b"56789"))
        assert crc.crcValue == 0x4B37


def _probe(**env: str) -> list[str]:
    code = (
        "import sys, pyrtu, pyrtu.compat.modbus_tk as tk;"
        "print(pyrtu.BACKEND, 'pyrtu.core._crcfast' in sys.modules,"
        " type(pyrtu.crc16).__name__, type(pyrtu.crc16_swapped).__name__,"
        " type(tk.calculate_crc).__name__)"
    )
    full = {k: v for k, v in os.environ.items() if not k.startswith("PYRTU_")}
    full.update(env, PYTHONPATH=str(ROOT))
    out = subprocess.run(
        [sys.executable, "-c", code], env=full, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_pure_switch_never_loads_it() -> None:
    _fast()
    assert _probe(PYRTU_PURE="1") == ["python", "False", "function", "function", "function"]
    default = _probe()
    assert (
        default == ["c", "True", "builtin_function_or_method"] + ["builtin_function_or_method"] * 2
    )
