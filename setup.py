"""Build the optional native tile kernel (dqm/core/_tilekernel.c).

The kernel is plain C loaded with ctypes (no Python C API), so a failed
compile is not fatal: dqm then uses its numpy implementation of the same
computation (see dqm/core/native.py).
"""
import sys

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext


class OptionalBuildExt(build_ext):
    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as exc:  # compiler missing or failing: fall back to numpy
            print(f"warning: native kernel not built ({exc}); dqm will use numpy", file=sys.stderr)

    def get_export_symbols(self, ext):
        return []  # loaded with ctypes, no PyInit_ symbol


setup(
    ext_modules=[
        Extension(
            "dqm.core._tilekernel",
            sources=["dqm/core/_tilekernel.c"],
            extra_compile_args=["-O3", "-std=c99", "-fno-math-errno"],
        )
    ],
    cmdclass={"build_ext": OptionalBuildExt},
)
