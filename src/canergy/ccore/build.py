"""The cffi builder of firmware/'s C library for Python: ``canergy.ccore._supervisor`` (what
``canergy supervisor --core c`` runs, room for every node id) and the sanitizer and broken
builds the tests drive (``load``: tests/support/c_binding.py, and ``CompiledSupervisor`` given
one of them).

The declarations are not written here: ``declarations`` runs the C preprocessor on the public
headers (firmware/include/canergy/*.h) and hands cffi what they declare, so the headers are the
one description of the C ABI. cffi's API mode then compiles against the same headers and
checks every struct it was given against the compiler's layout.

setup.py builds the release module where a C compiler exists (``pip install``); without one
canergy installs without it and ``canergy supervisor`` runs the Python core.
``python -m canergy.ccore.build`` builds it in place (a checkout whose install skipped it);
``--variant ubsan`` (``asan``, ``broken``, ``witnessed_only``) compiles that build into
``CACHE`` (scripts/test does, before the tests).
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from cffi import FFI

ROOT = Path(__file__).resolve().parents[3]
_SRCS = re.compile(r"^SRCS :=((?:.*\\\n)*.*)$", re.M)


def sources(root: Path = ROOT) -> tuple[str, ...]:
    """The library's sources as firmware/Makefile's SRCS lists them, then the host's frame path
    (canergy/host.h, src/host.c) that only this extension links."""
    makefile = (root / "firmware" / "Makefile").read_text()
    found = _SRCS.search(makefile)
    if found is None:
        raise RuntimeError("firmware/Makefile has no SRCS := line")
    names = found.group(1).replace("\\\n", " ").split()
    return (*(name.removeprefix("src/") for name in names), "host.c")


NODES = 127


@dataclass(frozen=True)
class Variant:
    """One build of the library: its module name and what it is compiled with."""

    module: str
    defines: tuple[tuple[str, str], ...] = ()
    cflags: tuple[str, ...] = ()
    ldflags: tuple[str, ...] = ()


_SANITIZE_FLAGS = ("-DCANERGY_ASSERTS", "-O1", "-g", "-fno-omit-frame-pointer")
_UBSAN = ("-fsanitize=undefined", "-fno-sanitize-recover=all")
_ASAN = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all")
_BREAKS = (
    ("CANERGY_BREAK_REPEATED_TX", "1"),
    ("CANERGY_BREAK_RETURN_AGAIN", "1"),
    ("CANERGY_BREAK_GIVE_BACK_KEEPS", "1"),
)

VARIANTS = {
    "release": Variant(
        "canergy.ccore._supervisor", (("CANERGY_SUPERVISOR_NODES", f"{NODES}U"),), ("-O2",)
    ),
    # The tests' builds keep the header's default of 16 sessions, as firmware/'s own tests do.
    # UBSan in-process: any report aborts the interpreter, so none can pass unnoticed.
    "ubsan": Variant("_canergy_ubsan", (), (*_SANITIZE_FLAGS, *_UBSAN), _UBSAN),
    # ASan: only in a process started with the ASan runtime preloaded (tests/test_c_asan.py).
    "asan": Variant("_canergy_asan", (), (*_SANITIZE_FLAGS, *_ASAN), _ASAN),
    # Deliberately broken rules that the side-by-side tests must find (tests/test_c_broken.py).
    "broken": Variant("_canergy_broken", _BREAKS, (*_SANITIZE_FLAGS, *_UBSAN), _UBSAN),
    # The witnessed rules alone, as the node port ships them (tests/test_c_witnessed.py).
    "witnessed_only": Variant(
        "_canergy_witnessed_only",
        (("CANERGY_RULES_WITNESSED_ONLY", "1"),),
        (*_SANITIZE_FLAGS, *_UBSAN),
        _UBSAN,
    ),
}


def _compiler() -> list[str]:
    return shlex.split(os.environ.get("CC", "cc"))


def _clang_runtime() -> tuple[str, ...]:
    """clang links its sanitizer runtimes statically unless told otherwise: a module CPython
    loads needs the shared ones, found where clang keeps them (firmware/Makefile's SAN_LINK did
    the same); nothing for gcc."""
    run = subprocess.run([*_compiler(), "--version"], capture_output=True, text=True, check=False)
    if "clang" not in run.stdout.lower():
        return ()
    where = subprocess.run(
        [*_compiler(), "-print-file-name=libclang_rt.ubsan_standalone-x86_64.so"],
        capture_output=True,
        text=True,
        check=False,
    ).stdout.strip()
    return ("-shared-libsan", f"-Wl,-rpath,{Path(where).parent}")


def _preprocess(text: str, include: Path, defines: tuple[tuple[str, str], ...], *flags: str) -> str:
    args = [f"-D{name}={value}" for name, value in defines]
    run = subprocess.run(
        [*_compiler(), "-E", "-std=c99", f"-I{include}", *args, *flags, "-x", "c", "-"],
        input=text,
        capture_output=True,
        text=True,
        check=False,
    )
    if run.returncode != 0:
        raise RuntimeError(f"the C preprocessor failed on the headers:\n{run.stderr}")
    return run.stdout


_MARKER = re.compile(r'^# \d+ "(.*)"')
_MACRO = re.compile(r"^#define (CANERGY_\w+) (\S.*)$")


def declarations(root: Path = ROOT, defines: tuple[tuple[str, str], ...] = ()) -> str:
    """cffi's cdef for every public header under ``root``: their declarations as the
    preprocessor leaves them (the system headers' dropped: cffi knows those types) and their
    object-like ``CANERGY_*`` macros as constants the compiler evaluates (``...``)."""
    include = root / "firmware" / "include"
    headers = sorted((include / "canergy").glob("*.h"))
    umbrella = "".join(f'#include "canergy/{h.name}"\n' for h in headers)
    kept: list[str] = []
    ours = False
    home = (include / "canergy").resolve()
    for line in _preprocess(umbrella, include, defines).splitlines():
        if marker := _MARKER.match(line):
            name = marker.group(1)
            ours = name == "<stdin>" or Path(name).resolve().parent == home
        elif ours and line.strip():
            kept.append(line)
    constants = sorted(
        f"#define {m.group(1)} ..."
        for line in _preprocess(umbrella, include, defines, "-dM").splitlines()
        if (m := _MACRO.match(line))
    )
    return "\n".join([*constants, *kept]) + "\n"


def builder(root: Path = ROOT, variant: str = "release") -> FFI:
    """The builder of one variant, naming firmware/ under ``root`` (setup.py needs paths
    relative to it)."""
    v = VARIANTS[variant]
    firmware = root / "firmware"
    ffi = FFI()
    ffi.cdef(declarations(root, v.defines))
    headers = sorted((firmware / "include" / "canergy").glob("*.h"))
    ffi.set_source(
        v.module,
        "".join(f'#include "canergy/{h.name}"\n' for h in headers),
        sources=[str(firmware / "src" / name) for name in sources(root)],
        include_dirs=[str(firmware / "include")],
        define_macros=list(v.defines),
        extra_compile_args=["-std=c99", *v.cflags],
        extra_link_args=[*v.ldflags, *(_clang_runtime() if v.ldflags else ())],
    )
    return ffi


def fingerprint(root: Path = ROOT, variant: str = "release") -> str:
    """A digest of what a variant is built from (sources, headers, flags, the compiler, the
    interpreter's extension ABI and cffi): a stale build shows."""
    import sysconfig

    import cffi

    firmware = root / "firmware"
    digest = hashlib.sha256(repr(VARIANTS[variant]).encode())
    digest.update(f"{sysconfig.get_config_var('EXT_SUFFIX')} {cffi.__version__}".encode())
    digest.update(" ".join(_compiler()).encode())
    digest.update(Path(__file__).read_bytes())
    tree = [*(firmware / "include").rglob("*.h"), *(firmware / "src").glob("*.[ch]")]
    for path in sorted([*tree, firmware / "Makefile"]):
        digest.update(path.name.encode() + path.read_bytes())
    return digest.hexdigest()[:16]


def compile_to(directory: Path, variant: str = "release") -> Path:
    """Compile one variant with its objects in ``directory``; returns the extension's path."""
    return Path(builder(variant=variant).compile(tmpdir=str(directory), verbose=False))


CACHE = ROOT / "firmware" / "build" / "cffi"
"""Where ``compiled`` keeps each variant, a directory per fingerprint."""


def compiled(variant: str, cache: Path = CACHE) -> Path:
    """The variant's extension, compiled once for these sources in
    ``cache/<variant>-<fingerprint>/`` (concurrent runs compile apart and the first to finish is
    kept; a source changed, it is compiled again beside the old one)."""
    import shutil
    import tempfile

    cache.mkdir(parents=True, exist_ok=True)
    target = cache / f"{variant}-{fingerprint(variant=variant)}"
    if not target.is_dir():
        work = Path(tempfile.mkdtemp(dir=cache, prefix=f".{variant}-"))
        try:
            compile_to(work, variant)
            work.rename(target)
        except OSError:
            if not target.is_dir():
                raise
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return next(target.rglob(f"{VARIANTS[variant].module.rpartition('.')[2]}.*.so"))


@functools.cache
def load(variant: str) -> ModuleType:
    """The variant's module (``ffi``, ``lib``), compiled if needed (``compiled``) and loaded once
    per process: what ``supervisor.CompiledSupervisor(module=...)`` runs and what the tests
    drive."""
    import importlib.util

    name = VARIANTS[variant].module
    spec = importlib.util.spec_from_file_location(name, compiled(variant))
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load the {variant} build of the C library")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def build_in_place() -> Path:
    """Compile the release module (``compiled``) and copy it into this checkout's source tree;
    returns the extension's path."""
    import shutil

    built = compiled("release")
    target = Path(__file__).parent / built.name
    shutil.copyfile(built, target)
    return target


def main(argv: list[str] | None = None) -> None:
    """``python -m canergy.ccore.build``: the release module in place; ``--variant NAME``
    (repeatable): those builds in ``CACHE`` (scripts/test builds the tests' ones first)."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m canergy.ccore.build",
        description="Build the release module into the source tree, or with --variant the "
        f"named builds into {CACHE} (printed).",
    )
    parser.add_argument(
        "--variant",
        action="append",
        choices=sorted(VARIANTS),
        default=[],
        help="a build to compile into the cache (repeatable)",
    )
    args = parser.parse_args(argv)
    for variant in args.variant or ["in place"]:
        print(build_in_place() if variant == "in place" else compiled(variant))


if __name__ == "__main__":
    main()
