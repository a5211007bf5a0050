"""Build glue: compiles the C core through cffi, or falls back to the pure-Python twin.

The cffi build script is pyrtu/core/_build_core.py (build time only). When no working C
compiler is present the install still succeeds, without the extension, and says so;
`import pyrtu` then selects the pure-Python backend (PYRTU_REQUIRE_C=1 refuses that).
Set PYRTU_REQUIRE_C=1 at build time to make a failed compile fail the install.

A second extension, ``pyrtu.core._crcfast`` (csrc/python/rtu_crc_py.c with csrc/rtu_crc.c,
the CPython API), gives the C backend's CRC functions a builtin's call cost; it is
optional in the same way (without it, the CRC goes through cffi) and is compiled with
the core's flags (PYRTU_STRICT_BUILD, PYRTU_SANITIZE: see pyrtu/core/_build_core.py).

The stable ABI: on CPython (not a debug or free-threaded build, which have none) both
extensions use the limited API of CPython 3.10 (cffi's module by cffi's default, the
CRC module by Py_LIMITED_API below), and the wheel is tagged cp310-abi3: one wheel per
platform for every CPython from 3.10 (docs/INSTALL.md).
"""

import importlib.util
import os
import platform
import sys
import sysconfig

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CRCFAST = "pyrtu.core._crcfast"
#: the oldest CPython the abi3 wheel runs on (pyproject.toml: requires-python)
LIMITED_API = (3, 10)
#: this interpreter builds against the stable ABI (as cffi decides for its module)
USE_LIMITED_API = (
    platform.python_implementation() == "CPython"
    and not hasattr(sys, "gettotalrefcount")  # a debug build
    and not sysconfig.get_config_var("Py_GIL_DISABLED")  # free-threaded: no abi3 before 3.15
)


def _core_flags() -> tuple[list[str], list[str]]:
    """The compile and link flags of pyrtu/core/_build_core.py (one place for them)."""
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "pyrtu", "core", "_build_core.py")
    spec = importlib.util.spec_from_file_location("_pyrtu_build_core", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return list(module.COMPILE_ARGS), list(module.LINK_ARGS)


class OptionalBuildExt(build_ext):
    """build_ext that turns a compile failure into a warning unless C is required."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:  # CCompilerError, DistutilsPlatformError, ...
            self._fallback(exc)

    def build_extension(self, ext) -> None:  # type: ignore[no-untyped-def]
        try:
            super().build_extension(ext)
        except Exception as exc:
            self._fallback(exc, ext.name)

    @staticmethod
    def _fallback(exc: BaseException, name: str = "") -> None:
        if os.environ.get("PYRTU_REQUIRE_C") == "1":
            raise exc
        if name == CRCFAST:
            sys.stderr.write(
                "\n*** pyrtu: the CRC module %s could not be compiled (%s).\n"
                "*** The C backend's CRC goes through cffi instead (slower per call).\n\n"
                % (CRCFAST, exc)
            )
            return
        # pip shows this only with -v; `import pyrtu` warns too (PureBackendWarning)
        sys.stderr.write(
            "\n*** pyrtu: the C core could not be compiled (%s).\n"
            "*** Installing the pure-Python backend only (pyrtu.BACKEND == 'python'):\n"
            "*** the stream parser runs some 85x slower and the exchange thread is gone.\n"
            "*** Install a C compiler, or a wheel (docs/INSTALL.md), and reinstall;\n"
            "*** PYRTU_REQUIRE_C=1 makes this an error.\n\n" % exc
        )


_compile_args, _link_args = _core_flags()
_limited_macros = [("Py_LIMITED_API", "0x%02X%02X0000" % LIMITED_API)] if USE_LIMITED_API else []

setup(
    cffi_modules=["pyrtu/core/_build_core.py:ffibuilder"],
    ext_modules=[
        Extension(
            CRCFAST,
            sources=["csrc/python/rtu_crc_py.c", "csrc/rtu_crc.c"],
            include_dirs=["csrc"],
            depends=["csrc/rtu_crc.h"],
            extra_compile_args=_compile_args,
            extra_link_args=_link_args,
            define_macros=_limited_macros,
            py_limited_api=USE_LIMITED_API,
        )
    ],
    cmdclass={"build_ext": OptionalBuildExt},
    options={"bdist_wheel": {"py_limited_api": "cp%d%d" % LIMITED_API}} if USE_LIMITED_API else {},
)
