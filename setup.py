"""Build glue: compiles the C core through cffi, or falls back to the pure-Python twin.

The cffi build script is pyrtu/core/_build_core.py (build time only). When no working C
compiler is present the install still succeeds, without the extension, and says so;
`import pyrtu` then selects the pure-Python backend (PYRTU_REQUIRE_C=1 refuses that).
Set PYRTU_REQUIRE_C=1 at build time to make a failed compile fail the install.

A second extension, ``pyrtu.core._crcfast`` (csrc/python/rtu_crc_py.c with csrc/rtu_crc.c,
the CPython API), gives the C backend's CRC functions a builtin's call cost; it is
optional in the same way (without it, the CRC goes through cffi) and is compiled with
the core's flags (PYRTU_STRICT_BUILD, PYRTU_SANITIZE: see pyrtu/core/_build_core.py).
"""

import importlib.util
import os
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

CRCFAST = "pyrtu.core._crcfast"


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
        sys.stderr.write(
            "\n*** pyrtu: the C core could not be compiled (%s).\n"
            "*** Installing the pure-Python backend only (pyrtu.BACKEND == 'python').\n\n" % exc
        )


_compile_args, _link_args = _core_flags()

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
        )
    ],
    cmdclass={"build_ext": OptionalBuildExt},
)
