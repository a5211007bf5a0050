"""CRC-16/MODBUS: the C core (dispatch and each path), the pure-Python twin and peers.

    python -m pytest bench/bench_crc.py -p no:cacheprovider [--benchmark-json=out.json]

Measurements, not tests: nothing about speed is asserted.  Groups "crc16 8 B",
"crc16 256 B", "crc16 1 MiB"; ``extra_info["bytes"]`` gives the size, so GB/s is
bytes / mean (or median) time.  ``c noop`` is an empty cffi call with no arguments,
``c noop same arguments`` one with crc16's (bytes, length, seed): the floors under
the cffi rows.  Both are functions of a small cffi module this file compiles at run
time into a temporary directory (`_noop_lib`, the same out-of-line API mode as
pyrtu.core._rtu_core), so that the shipped extension carries no benchmark-only code.
``c path <name>`` calls
``rtu_crc16_path`` straight through cffi with a preallocated buffer and result
(the C cost plus one cffi call); ``c crc16`` is the C backend's public function,
the builtin of pyrtu.core._crcfast when it is built (``builtin noop``, ``len(data)``, is
the floor under it), and ``c crc16 cffi`` the same through cffi.
Peers (crcmod, pymodbus, minimalmodbus) are skipped when not installed.

The same sizes measured in C alone (the function called in a loop; Zen 5 at about
4.2 GHz, gcc 12 -O2; median of 21 runs; GB/s, and ns per call):

                 each CRC feeds the next call        independent calls
    path         8 B     256 B    1 MiB              8 B     256 B    1 MiB
    bytewise     0.64    0.65     0.69               1.8     0.73     0.69
    slice8       2.9     6.0      6.3                2.8     5.9      6.2
    clmul        2.9*    15.2     16.2               2.6*    15.1     16.1
    vclmul       2.9*    20.0     64.6               2.7*    41.2     66.4
    rtu_crc16    2.8     19.3     64.3               2.7     38.8     65.5
    (8 B: 2.8 ns per call, an empty call is 1.4 ns; * below 48 / 64 bytes the
    folding paths run the slicing code; slice8 is slicing-by-16; the multiplier,
    one (V)PCLMULQDQ every 2 cycles, bounds clmul and vclmul)
"""

from __future__ import annotations

import importlib.util
import random
import tempfile
from collections.abc import Callable, Iterator
from typing import Any

import pytest

import pyrtu

SIZES = {"8 B": 8, "256 B": 256, "1 MiB": 1 << 20}
PATHS = ("bytewise", "slice8", "clmul", "vclmul")


@pytest.fixture(scope="module", params=list(SIZES))
def payload(request: pytest.FixtureRequest) -> tuple[str, bytes]:
    label = request.param
    return label, random.Random(SIZES[label]).randbytes(SIZES[label])


def _c() -> Any:
    if "c" not in pyrtu.available_backends():
        pytest.skip("the C core is not built")
    from pyrtu.core import _cext

    return _cext


def _run(
    benchmark: Any, label: str, data: bytes, fn: Callable[..., object], *args: object
) -> object:
    """Time ``fn(*args)``: the function itself is called by the timer, with no wrapper
    around it, so every row pays the same single call."""
    benchmark.group = f"crc16 {label}"
    benchmark.extra_info["bytes"] = len(data)
    if len(data) >= 1 << 20:  # slow pure-Python peers: a few rounds are plenty
        return benchmark.pedantic(fn, args=args, rounds=5, iterations=1, warmup_rounds=1)
    return benchmark(fn, *args)


def _want(data: bytes) -> int:
    return int(pyrtu.backend("python").crc16(data[:4096])) if len(data) <= 4096 else -1


_NOOP_CDEF = """
void bench_noop(void);
uint16_t bench_noop_bytes(const char *data, size_t len, uint16_t crc);
"""
# the same shapes as the core's crc16 bindings (pyrtu/core/_build_core.py), doing nothing
_NOOP_SOURCE = """
#include <stddef.h>
#include <stdint.h>
void bench_noop(void)
{
}
uint16_t bench_noop_bytes(const char *data, size_t len, uint16_t crc)
{
    (void)data;
    (void)len;
    return crc;
}
"""


@pytest.fixture(scope="module")
def _noop_lib() -> Iterator[Any]:
    """The ``lib`` of an out-of-line cffi module of two empty functions, compiled
    into a temporary directory (skips when cffi or a C compiler is missing)."""
    cffi = pytest.importorskip("cffi")
    with tempfile.TemporaryDirectory(prefix="pyrtu-bench-noop-") as tmp:
        ffi = cffi.FFI()
        ffi.cdef(_NOOP_CDEF)
        ffi.set_source("_pyrtu_bench_noop", _NOOP_SOURCE)
        try:
            path = ffi.compile(tmpdir=tmp)
        except Exception as exc:  # cffi.VerificationError, distutils' CompileError
            pytest.skip(f"cannot compile the empty cffi module: {exc}")
        spec = importlib.util.spec_from_file_location("_pyrtu_bench_noop", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module.lib


def test_c_noop(benchmark: Any, payload: tuple[str, bytes], _noop_lib: Any) -> None:
    """An empty C function with no arguments: the floor of any cffi call."""
    label, data = payload
    _run(benchmark, label, data, _noop_lib.bench_noop)


def test_c_noop_same_arguments(benchmark: Any, payload: tuple[str, bytes], _noop_lib: Any) -> None:
    """An empty C function with crc16's arguments (bytes, length, seed): the floor of
    any cffi call of this shape."""
    label, data = payload
    result = _run(benchmark, label, data, _noop_lib.bench_noop_bytes, data, len(data), 0xFFFF)
    assert result == 0xFFFF


def test_c_crc16(benchmark: Any, payload: tuple[str, bytes]) -> None:
    label, data = payload
    _c()
    c = pyrtu.backend("c")
    result = _run(benchmark, label, data, c.crc16, data)
    assert _want(data) in (-1, result)


def test_c_crc16_cffi(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """``c crc16`` through cffi (the C backend's function when pyrtu.core._crcfast is not
    built, and before it was written): the same C, a cffi call's overhead."""
    label, data = payload
    cext = _c()
    result = _run(benchmark, label, data, cext._cffi_crc16, data)
    assert _want(data) in (-1, result)


def test_c_crc16_swapped(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """``pyrtu.crc16_swapped``: modbus_tk's ``calculate_crc`` shape (pyrtu.compat)."""
    label, data = payload
    _c()
    from pyrtu.core import crcshapes as _crcshapes

    result = _run(benchmark, label, data, _crcshapes.crc16_swapped, data)
    want = _want(data)
    assert want == -1 or result == ((want & 0xFF) << 8 | want >> 8)


def test_c_crc16_swapped_cffi(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """The same shape over cffi (what ``crc16_swapped`` was before pyrtu.core._crcfast)."""
    label, data = payload
    _c()
    from pyrtu.core import crcshapes as _crcshapes

    _run(benchmark, label, data, _crcshapes._crc16_swapped, data)


def test_builtin_noop(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """``len(data)``: a builtin called with one argument, the floor under the rows that
    call pyrtu.core._crcfast (its functions are builtins too)."""
    label, data = payload
    _run(benchmark, label, data, len, data)


def test_c_rtu_crc16_raw(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """The dispatcher through cffi, no argument checking (the C floor of ``c crc16``)."""
    label, data = payload
    cext = _c()
    lib, buf, n = cext.lib, cext.ffi.from_buffer("uint8_t[]", data), len(data)
    result = _run(benchmark, label, data, lib.rtu_crc16, buf, n, 0xFFFF)
    assert _want(data) in (-1, result)


@pytest.mark.parametrize("path", PATHS)
def test_c_path(benchmark: Any, payload: tuple[str, bytes], path: str) -> None:
    label, data = payload
    cext = _c()
    if path not in cext.crc16_paths():
        pytest.skip(f"this CPU cannot run the {path} path")
    lib, ffi = cext.lib, cext.ffi
    code = getattr(lib, f"RTU_CRC_{path.upper()}")
    buf, n, out = ffi.from_buffer("uint8_t[]", data), len(data), ffi.new("uint16_t *")

    def run() -> int:
        lib.rtu_crc16_path(code, buf, n, 0xFFFF, out)
        return int(out[0])

    result = _run(benchmark, label, data, run)
    assert result == cext.crc16(data)


def test_python_twin(benchmark: Any, payload: tuple[str, bytes]) -> None:
    label, data = payload
    py = pyrtu.backend("python")
    _run(benchmark, label, data, py.crc16, data)


def test_crcmod(benchmark: Any, payload: tuple[str, bytes]) -> None:
    label, data = payload
    predefined = pytest.importorskip("crcmod.predefined")
    fn = predefined.mkCrcFun("modbus")
    result = _run(benchmark, label, data, fn, data)
    assert _want(data) in (-1, result)


def test_pymodbus(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """pymodbus 3.x: ``FramerRTU.compute_CRC`` (returns the CRC byte-swapped)."""
    label, data = payload
    rtu = pytest.importorskip("pymodbus.framer.rtu")
    fn = rtu.FramerRTU.compute_CRC
    result = _run(benchmark, label, data, fn, data)
    want = _want(data)
    assert want == -1 or result == ((want & 0xFF) << 8 | want >> 8)


def test_minimalmodbus(benchmark: Any, payload: tuple[str, bytes]) -> None:
    """minimalmodbus: ``_calculate_crc_string`` (1.x, str) or ``_calculate_crc`` (2.x, bytes)."""
    label, data = payload
    mm = pytest.importorskip("minimalmodbus")
    if hasattr(mm, "_calculate_crc_string"):
        text = data.decode("latin-1")

        def fn() -> object:
            return mm._calculate_crc_string(text)
    elif hasattr(mm, "_calculate_crc"):

        def fn() -> object:
            return mm._calculate_crc(data)
    else:
        pytest.skip("minimalmodbus has no CRC helper by a known name")
    _run(benchmark, label, data, fn)
