"""cffi build script for the C core (build time only; never imported at run time).

Developers: `python setup.py build_ext --inplace` (or `pip install -e .`).

Compiles every csrc/*.c into the extension module ``pyrtu.core._rtu_core``.  The
declarations cffi needs live in pyrtu/core/_cdef.h.  PYRTU_SANITIZE=1 builds with
AddressSanitizer and UBSan (for the CI sanitizer run).

PYRTU_STRICT_BUILD=1 turns warnings into errors (``-Werror``): CI and the
Makefile's developer targets set it, so that the code stays ``-Wall -Wextra``
clean.  A user's ``pip install`` does not: a warning that a newer compiler adds
must not cost them the C core (setup.py would fall back to the slow twin).
"""

import os
import pathlib

from cffi import FFI

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent.parent
CSRC = ROOT / "csrc"

ffibuilder = FFI()
ffibuilder.cdef((HERE / "_cdef.h").read_text())

_flags = ["-std=c99", "-O2", "-Wall", "-Wextra"]
if os.environ.get("PYRTU_STRICT_BUILD") == "1":
    _flags.append("-Werror")
_link: list[str] = []
if os.environ.get("PYRTU_SANITIZE") == "1":
    _san = [
        "-fsanitize=address,undefined",
        "-fno-sanitize-recover=undefined",
        "-fno-omit-frame-pointer",
        "-g",
    ]
    _flags += _san
    _link += _san
# the same flags for the CPython-API CRC module (setup.py: pyrtu.core._crcfast)
COMPILE_ARGS, LINK_ARGS = tuple(_flags), tuple(_link)

# Binding-only helper: cffi passes a ``bytes`` object to a ``const char *``
# parameter without a copy and refuses every other type, which gives crc16 a
# fast path that checks the type for free.
_BINDING = """
#include "rtu.h"
#include "rtu_vbus.h"
#include "rtu_xfer.h"
static uint16_t rtu_crc16_bytes(const char *data, size_t len, uint16_t crc)
{
    return rtu_crc16((const uint8_t *)data, len, crc);
}
"""

ffibuilder.set_source(
    "pyrtu.core._rtu_core",
    _BINDING,
    sources=[os.path.relpath(p, ROOT) for p in sorted(CSRC.glob("*.c"))],
    include_dirs=[os.path.relpath(CSRC, ROOT)],
    extra_compile_args=_flags,
    extra_link_args=_link,
)
