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
SOURCES = (
    "codec.c",
    "nv.c",
    "client.c",
    "node.c",
    "aes128.c",
    "cmac.c",
    "auth.c",
    "session.c",
    "supervisor.c",
    "gateway.c",
    "witness.c",
    "telemetry.c",
    "grants.c",
    "joins.c",
)
"""The whole library (firmware/Makefile's SRCS)."""
NODES = 127

HOST_DECLARATIONS = """
#define CANERGY_HOST_HELD 0x1000000U /* canergy_host_answer's verdict: a RETURN the witness took */
#define CANERGY_HOST_JOIN 0x2000000U /* canergy_host_answer's verdict: a JOIN held */
struct canergy_host_tables { /* the service's tables in C, one record per session each */
    struct canergy_heard *heard;
    struct canergy_witness *witness;
    struct canergy_joins *joins;
    const uint64_t *join_hold_us; /* per session: how long a confirmed JOIN waits */
    struct canergy_witness witness_before; /* the record the last call changed, as it was */
    struct canergy_joins joins_before;
    uint64_t lost_after_us;
    unsigned verdict;
    uint16_t admit; /* verdict's CANERGY_JOINS_ADMIT: the JOIN to admit */
    bool hold;      /* hold fresh RETURNs (no key) */
};
int canergy_host_answer(struct canergy_supervisor *sup, struct canergy_host_tables *t,
    uint32_t id, unsigned kind, const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_msg *m);
"""
"""What only the host's binding calls: declared once, for cffi and (its definition's head, below)
for the compiler."""

_HOST_AUTH_ANSWER = """
int canergy_host_auth_answer(struct canergy_supervisor *sup, struct canergy_auth *keys,
    uint32_t id, unsigned kind, const uint8_t *data, size_t len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_auth_frame *sent, uint8_t *sent_count,
    uint32_t *fv);"""
_HOST_AUTH_PROTECT = """
void canergy_host_auth_protect(const struct canergy_supervisor *sup,
    const struct canergy_auth *keys, const struct canergy_supervisor_out *out,
    struct canergy_auth_frame *sent, uint8_t *sent_count);"""
_HOST_AUTH_PAIR = """
int canergy_host_auth_pair(struct canergy_supervisor *sup, struct canergy_auth *keys,
    uint32_t data_id, const uint8_t *data, size_t data_len, uint32_t mac_id, unsigned mac_kind,
    const uint8_t *mac, size_t mac_len, uint64_t now, bool abort_acks,
    struct canergy_supervisor_out *out, struct canergy_auth_frame *sent, uint8_t *sent_count,
    uint32_t *fv);"""
HOST_AUTH_DECLARATIONS = _HOST_AUTH_ANSWER + _HOST_AUTH_PROTECT + _HOST_AUTH_PAIR + "\n"
"""The fast path with ``--auth``: FD layout (``CompiledSupervisor.on_auth_answer``), classic
layout (``on_auth_pair``), and ``begin_protected`` in either."""

HOST_SOURCE = (
    """
/* The session index of node, or sup->count when it is not managed. */
static uint8_t canergy_host_index(const struct canergy_supervisor *sup, uint32_t node)
{
    uint8_t i = 0U;
    while (i < sup->count && sup->sessions[i].node != node) {
        i++;
    }
    return i;
}

/* The fast path's call with the frame as arguments: one call, no struct filled field by field
   from Python (kind: bit 0 extended identifier, bit 1 remote frame). An ACK, COMMITTED or
   ABORTED of a managed node as canergy_supervisor_on_answer takes it. With the tables (t NULL:
   none, and the rest below is the caller's), for a managed node:
   - a TELEMETRY is taken by the TELEMETRY table, the witness and the held JOINs: t->verdict is
     the table's verdict, the witness's findings shifted left by 8 and the JOINs' by 16 (the
     JOIN to admit in t->admit); status CANERGY_RX_CALLER;
   - a RETURN the books allow: without hold, or an old number, to the rules (CANERGY_DECODE_OK,
     out as for an ACK, verdict 0); else held by the witness, verdict CANERGY_HOST_HELD with the
     witness's verdict (CANERGY_RX_CALLER);
   - a JOIN is held: verdict CANERGY_HOST_JOIN (CANERGY_RX_CALLER);
   the records as they were before, in t->witness_before and t->joins_before. Anything else (a
   RETURN beyond the books among it) leaves the verdict 0: the caller's. */"""
    + HOST_DECLARATIONS.rstrip().removesuffix(";")
    + """
{
    struct canergy_rx_frame rx = {0};
    rx.id = id;
    rx.data = data;
    rx.len = len;
    rx.extended = (kind & 1U) != 0U;
    rx.remote = (kind & 2U) != 0U;
    const int status = canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, m);
    if (t == NULL) {
        return status;
    }
    t->verdict = 0U;
    if (status != CANERGY_RX_CALLER) {
        return status;
    }
    const uint8_t i = canergy_host_index(sup, m->node);
    struct canergy_session *s = &sup->sessions[i];
    if (m->type == CANERGY_TELEMETRY) {
        t->verdict = canergy_heard_telemetry(&t->heard[i], s, m, now, t->lost_after_us);
        t->witness_before = t->witness[i];
        t->verdict |= canergy_witness_telemetry(&t->witness[i], m, s->returns_credited, now) << 8;
        t->joins_before = t->joins[i];
        t->verdict |= canergy_joins_telemetry(&t->joins[i], m->flags, now, t->join_hold_us[i],
                                              &t->admit) << 16;
        return status;
    }
    if (m->type == CANERGY_JOIN) {
        canergy_joins_join(&t->joins[i], m->nonce);
        t->verdict = CANERGY_HOST_JOIN;
        return status;
    }
    if (m->type != CANERGY_RETURN || canergy_witness_beyond_books(s, m)) {
        return status;
    }
    const uint32_t ahead = (m->seq - s->returns_credited) & 0xFFFFU; /* Python's unwrap - ref */
    if (t->hold && ahead != 0U && ahead < 0x8000U) {                   /* not credited yet */
        t->witness_before = t->witness[i];
        t->verdict = CANERGY_HOST_HELD |
                     (unsigned)canergy_witness_hold(&t->witness[i], m, s->returns_credited, now);
        return status;
    }
    return canergy_supervisor_on_msg(sup, m, now, out);
}

/* Authenticated mode: each of out's frames protected under its node's key (keys: one per
   session, in the sessions' order) with its session's counters, in order: one FD frame each,
   or in the classic layout two (the frame, then its MAC frame). */"""
    + _HOST_AUTH_PROTECT.removesuffix(";")
    + """
{
    *sent_count = 0U;
    for (uint8_t k = 0U; k < out->frame_count; k++) {
        const uint8_t j = canergy_host_index(sup, out->frames[k].id & 0xFFU);
        struct canergy_auth_frame two[2];
        const int made = j < sup->count ? canergy_auth_protect(&keys[j], &out->frames[k],
                                                                sup->sessions[j].tx,
                                                                sup->sessions[j].returns_credited,
                                                                two)
                                         : 0;
        for (int f = 0; f < made; f++) { /* none: each frame the rules send is a managed */
            sent[(*sent_count)++] = two[f]; /* node's, encoded by the codec */
        }
    }
}

/* Authenticated mode, FD layout (keys: one per session, in the sessions' order, receiving
   CANERGY_TO_SUPERVISOR): an ACK, COMMITTED or ABORTED of a managed node verified as Python's
   FrameAuth verifies it (MAC, then an FV that is the expected one and not before the
   session's tx), the rules run and each frame they send protected. Any other frame, or one
   that fails any check or that the rules leave to the caller, returns a status other than
   CANERGY_DECODE_OK before anything changed (an FD frame leaves no state in keys): the caller
   takes it the usual way, where a refusal is counted. *fv: the verified frame's FV. */"""
    + _HOST_AUTH_ANSWER.removesuffix(";")
    + """
{
    *sent_count = 0U;
    const uint32_t type = id >> 8 & 0xFU;
    if ((kind & 3U) != 1U || id > 0x1FFFFFFFUL || (id & CANERGY_ID_MASK) != sup->id_base ||
        (type != CANERGY_ACK && type != CANERGY_COMMITTED && type != CANERGY_ABORTED)) {
        return CANERGY_RX_CALLER;
    }
    const uint8_t i = canergy_host_index(sup, id & 0xFFU);
    if (i == sup->count || keys[i].layout != CANERGY_AUTH_FD) {
        return CANERGY_RX_OTHER_NODE;
    }
    const struct canergy_session *s = &sup->sessions[i];
    struct canergy_rx_frame rx = {0};
    rx.id = id;
    rx.data = data;
    rx.len = len;
    rx.extended = true;
    struct canergy_frame plain;
    int status = canergy_auth_accept(&keys[i], &rx, s->tx, s->returns_credited, &plain);
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    const uint8_t *t = &data[len - CANERGY_AUTH_TRAILER];
    const uint32_t got = (uint32_t)t[0] << 24 | (uint32_t)t[1] << 16 | (uint32_t)t[2] << 8 | t[3];
    if (got != s->tx && (uint32_t)(s->tx - got) < 0x80000000UL) {
        return CANERGY_AUTH_STALE; /* before the session's tx: a replay (Python's _older) */
    }
    struct canergy_msg m;
    rx.data = plain.data;
    rx.len = plain.dlc;
    status = canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, &m);
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    *fv = got;
    canergy_host_auth_protect(sup, keys, out, sent, sent_count);
    return CANERGY_DECODE_OK;
}

/* Authenticated mode, classic layout (keys as above, each CANERGY_AUTH_CLASSIC): a message and
   the MAC frame that completes it (the caller pairs them and keeps the message until its MAC
   frame, as Python's FrameAuth does; mac_kind as canergy_host_answer's kind). An ACK, COMMITTED
   or ABORTED of a managed node verified as FrameAuth verifies the pair (MAC, then an FV that is
   the expected one and not before the session's tx), the rules run and each frame they send
   protected (two frames each). Any other pair, or one that fails any check or that the rules
   leave to the caller, returns a status other than CANERGY_DECODE_OK before anything changed
   (the key's waiting slot is empty again): the caller takes the MAC frame the usual way, where
   the pair is judged and a refusal counted. *fv: the verified pair's FV. */"""
    + _HOST_AUTH_PAIR.removesuffix(";")
    + """
{
    *sent_count = 0U;
    const uint32_t type = data_id >> 8 & 0xFU;
    const uint32_t mac_of = (data_id & ~0xF00UL) | (uint32_t)CANERGY_AUTH_MAC_TO_SUPERVISOR << 8;
    if ((mac_kind & 3U) != 1U || data_id > 0x1FFFFFFFUL ||
        (data_id & CANERGY_ID_MASK) != sup->id_base || mac_id != mac_of ||
        (type != CANERGY_ACK && type != CANERGY_COMMITTED && type != CANERGY_ABORTED)) {
        return CANERGY_RX_CALLER;
    }
    const uint8_t i = canergy_host_index(sup, data_id & 0xFFU);
    if (i == sup->count || keys[i].layout != CANERGY_AUTH_CLASSIC) {
        return CANERGY_RX_OTHER_NODE;
    }
    struct canergy_auth *a = &keys[i];
    const struct canergy_session *s = &sup->sessions[i];
    struct canergy_rx_frame rx = {0};
    rx.id = data_id;
    rx.data = data;
    rx.len = data_len;
    rx.extended = true;
    struct canergy_frame plain;
    a->pending_len = 0U;
    int status = canergy_auth_accept(a, &rx, s->tx, s->returns_credited, &plain);
    if (status != CANERGY_AUTH_PENDING) {
        a->pending_len = 0U;
        return status == CANERGY_DECODE_OK ? CANERGY_RX_CALLER : status;
    }
    rx.id = mac_id;
    rx.data = mac;
    rx.len = mac_len;
    status = canergy_auth_accept(a, &rx, s->tx, s->returns_credited, &plain);
    a->pending_len = 0U; /* taken by the MAC frame whatever it was */
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    struct canergy_msg m;
    rx.id = plain.id;
    rx.data = plain.data;
    rx.len = plain.dlc;
    if (canergy_decode(sup->id_base, &rx, CANERGY_TO_SUPERVISOR, &m) != CANERGY_DECODE_OK) {
        return CANERGY_RX_CALLER; /* it was verified, so it decoded: not reached */
    }
    const uint32_t got = ((uint32_t)mac[1] << 8 | mac[2]) << 16 |
                         (canergy_auth_freshness(&m, 0U, 0U) & 0xFFFFUL);
    if (got != s->tx && (uint32_t)(s->tx - got) < 0x80000000UL) {
        return CANERGY_AUTH_STALE; /* before the session's tx: a replay (Python's _older) */
    }
    status = canergy_supervisor_on_answer(sup, &rx, now, abort_acks, out, &m);
    if (status != CANERGY_DECODE_OK) {
        return status;
    }
    *fv = got;
    canergy_host_auth_protect(sup, keys, out, sent, sent_count);
    return CANERGY_DECODE_OK;
}
"""
)


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
    umbrella += HOST_DECLARATIONS + HOST_AUTH_DECLARATIONS
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
        "".join(f'#include "canergy/{h.name}"\n' for h in headers) + HOST_SOURCE,
        sources=[str(firmware / "src" / name) for name in SOURCES],
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
    digest = hashlib.sha256(repr(VARIANTS[variant]).encode() + HOST_SOURCE.encode())
    digest.update(f"{sysconfig.get_config_var('EXT_SUFFIX')} {cffi.__version__}".encode())
    digest.update(" ".join(_compiler()).encode())
    digest.update(Path(__file__).read_bytes())
    for path in sorted([*(firmware / "include").rglob("*.h"), *(firmware / "src").glob("*.[ch]")]):
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
