"""Builds the compiled supervisor core (canergy.ccore._supervisor, cffi) where a C compiler
exists; without one canergy installs without it and runs the Python core (``--core python``).
Everything else is in pyproject.toml."""

import sys

from setuptools import setup
from setuptools.command.build_ext import build_ext

sys.path.insert(0, "src")
from pathlib import Path

from canergy.ccore.build import builder


class OptionalBuildExt(build_ext):
    """A failed compile is a warning, not a failed install: the Python core is the fallback."""

    def run(self) -> None:
        try:
            super().run()
        except Exception as exc:  # no compiler, no Python headers
            print(
                f"canergy: the C supervisor core was not built ({exc}); "
                "canergy supervisor will run the Python core",
                file=sys.stderr,
            )

    def build_extension(self, ext) -> None:  # type: ignore[no-untyped-def]
        try:
            super().build_extension(ext)
        except Exception as exc:
            print(
                f"canergy: the C supervisor core was not built ({exc}); "
                "canergy supervisor will run the Python core",
                file=sys.stderr,
            )


def extensions() -> list:  # type: ignore[type-arg]
    """The release module, its declarations read from the headers by the C preprocessor: none
    (the Python core) where there is no compiler to read them."""
    try:
        return [builder(Path(".")).distutils_extension(tmpdir="build/cffi")]
    except Exception as exc:
        print(
            f"canergy: the C supervisor core was not built ({exc}); "
            "canergy supervisor will run the Python core",
            file=sys.stderr,
        )
        return []


setup(
    ext_modules=extensions(),
    cmdclass={"build_ext": OptionalBuildExt},
)
