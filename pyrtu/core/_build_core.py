"""cffi build script for the C core (build time only; never imported at run time).

Developers: `python setup.py build_ext --inplace` (or `pip install -e .`).

Compiles the csrc/*.c files into the extension module ``pyrtu.core._rtu_core``.  The
declarations cffi needs live in pyrtu/core/_cdef.h.  PYRTU_SANITIZE=1 builds with
AddressSanitizer and UBSan (for the CI sanitizer run).

The POSIX I/O files, csrc/rtu_*_io.c (the master's exchange thread, rtu_xfer_io.c, and
the virtual bus's I/O loop, rtu_vbus_io.c: ppoll, pthreads, termios), are compiled only
where the platform is POSIX (`POSIX_IO`); elsewhere (Windows) they and their
declarations (the "POSIX I/O" sections of _cdef.h) are left out, and the C backend's
``POSIX_IO`` (pyrtu/core/_cext.py) is False: the twin's exchange and the Python hub
loop run instead, while CRC, framers and parsers stay in C.  Everything else in csrc/ is
portable C99 (`make cross-windows` compiles it with mingw-w64 and -Werror).
PYRTU_POSIX_IO=0 builds the Windows set on a POSIX machine (tests/core/test_portable_core.py).

The module uses the stable ABI (cffi's default: ``.abi3`` on CPython); setup.py builds
the CRC builtins (pyrtu.core._crcfast) on the same one and tags the wheel cp310-abi3.

PYRTU_STRICT_BUILD=1 turns warnings into errors (``-Werror``): CI and the
Makefile's developer targets set it, so that the code stays ``-Wall -Wextra``
clean.  A user's ``pip install`` does not: a warning that a newer compiler adds
must not cost them the C core (setup.py would fall back to the slow twin).
"""

import os
import pathlib
import re
import subprocess
import sys

from cffi import FFI

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent.parent
CSRC = ROOT / "csrc"

#: the POSIX I/O files of csrc/ (a name ending in _io.c) are compiled here
POSIX_IO = os.environ.get("PYRTU_POSIX_IO", "0" if sys.platform == "win32" else "1") == "1"
#: the "POSIX I/O" sections of _cdef.h (the declarations of csrc/rtu_*_io.c)
_POSIX_CDEF = re.compile(r"/\* ---- POSIX I/O .*?/\* ---- end of POSIX I/O ---- \*/", re.S)


#: the TLS of an mbaps:// client (csrc/rtu_tls_io.c, over the system's OpenSSL) is
#: compiled where OpenSSL's development files are found (``pkg-config openssl``;
#: Debian: libssl-dev) on a POSIX build; elsewhere, or with PYRTU_TLS=0, it and its
#: declarations (the "TLS" section of _cdef.h) are left out and ``mbaps://`` runs
#: over Python's ssl module (pyrtu/tcp/tls.py)
TLS_SOURCE = "rtu_tls_io.c"
_TLS_CDEF = re.compile(r"/\* ---- TLS .*?/\* ---- end of TLS ---- \*/", re.S)


def openssl_flags() -> tuple[list[str], list[str]] | None:
    """(compile, link) flags of the system's OpenSSL (pkg-config), None without it."""
    if not POSIX_IO or os.environ.get("PYRTU_TLS", "1") == "0":
        return None
    try:
        cflags = subprocess.run(
            ["pkg-config", "--cflags", "openssl"], capture_output=True, text=True, check=True
        ).stdout.split()
        libs = subprocess.run(
            ["pkg-config", "--libs", "openssl"], capture_output=True, text=True, check=True
        ).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        return None
    return cflags, libs


OPENSSL = openssl_flags()


def is_posix_io(path: pathlib.Path) -> bool:
    """A POSIX-only file of csrc/ (the naming rule; tests/core/test_portable_core.py
    checks that the POSIX headers appear only in these)."""
    return path.name.endswith("_io.c")


def core_sources() -> list[pathlib.Path]:
    """The csrc/*.c files compiled into the core on this platform."""
    return [
        p
        for p in sorted(CSRC.glob("*.c"))
        if (POSIX_IO or not is_posix_io(p)) and (OPENSSL is not None or p.name != TLS_SOURCE)
    ]


def core_cdef() -> str:
    """_cdef.h, without its POSIX I/O sections where those files are not compiled
    (and without its TLS section where OpenSSL is not found)."""
    text = (HERE / "_cdef.h").read_text()
    if OPENSSL is None:
        text = _TLS_CDEF.sub("", text)
    return text if POSIX_IO else _POSIX_CDEF.sub("", text)


ffibuilder = FFI()
ffibuilder.cdef(core_cdef())

#: MSVC (CPython's compiler on Windows) takes its own flags; every other compiler
#: here is GCC-like (gcc, clang, mingw-w64)
MSVC = sys.platform == "win32" and "MSC v." in sys.version
if MSVC:
    _flags = ["/O2", "/W3"]
    if os.environ.get("PYRTU_STRICT_BUILD") == "1":
        _flags.append("/WX")
else:
    _flags = ["-std=c99", "-O2", "-Wall", "-Wextra"]
    if os.environ.get("PYRTU_STRICT_BUILD") == "1":
        _flags.append("-Werror")
_link: list[str] = []
if os.environ.get("PYRTU_SANITIZE") == "1" and not MSVC:
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
#include "rtu_tcp.h"
#include "rtu_mux.h"
#include "rtu_image.h"
#include "rtu_serve.h"
%s
static uint16_t rtu_crc16_bytes(const char *data, size_t len, uint16_t crc)
{
    return rtu_crc16((const uint8_t *)data, len, crc);
}
"""

_BINDING %= '#include "rtu_tls.h"' if OPENSSL is not None else ""

ffibuilder.set_source(
    "pyrtu.core._rtu_core",
    _BINDING,
    sources=[os.path.relpath(p, ROOT) for p in core_sources()],
    include_dirs=[os.path.relpath(CSRC, ROOT)],
    extra_compile_args=_flags + ([] if OPENSSL is None else OPENSSL[0]),
    extra_link_args=_link + ([] if OPENSSL is None else OPENSSL[1]),
)
