"""Build glue: compiles the C core through cffi, or falls back to the pure-Python twin.

The cffi build script is pyrtu/_build_core.py (build time only). When no working C
compiler is present the install still succeeds, without the extension, and says so;
`import pyrtu` then selects the pure-Python backend (PYRTU_REQUIRE_C=1 refuses that).
Set PYRTU_REQUIRE_C=1 at build time to make a failed compile fail the install.
"""

import os
import sys

from setuptools import setup
from setuptools.command.build_ext import build_ext


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
            self._fallback(exc)

    @staticmethod
    def _fallback(exc: BaseException) -> None:
        if os.environ.get("PYRTU_REQUIRE_C") == "1":
            raise exc
        sys.stderr.write(
            "\n*** pyrtu: the C core could not be compiled (%s).\n"
            "*** Installing the pure-Python backend only (pyrtu.BACKEND == 'python').\n\n" % exc
        )


setup(
    cffi_modules=["pyrtu/_build_core.py:ffibuilder"],
    cmdclass={"build_ext": OptionalBuildExt},
)
