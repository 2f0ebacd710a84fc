"""The C-vs-Python tests again under AddressSanitizer (and UBSan), in a child pytest.

Why a child process: an ASan-instrumented shared object can only be loaded into a process whose
first library is the ASan runtime, so CPython has to be started with it preloaded
(``LD_PRELOAD``); leak checking is off because CPython itself keeps memory until exit. The
in-process runs use the UBSan-only build, which needs no preloading. In both builds every
sanitizer report aborts (``-fno-sanitize-recover=all``), so a report cannot pass: here the
child's exit status and its output are both checked.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from support.c_binding import FIRMWARE, compiled

TESTS = Path(__file__).resolve().parent
UNDER_ASAN = [
    "test_c_auth.py",
    "test_c_binding.py",
    "test_ccore.py",
    "test_ccore_buses.py",
    "test_c_codec.py",
    "test_c_cmac.py",
    "test_c_hardened.py",
    "test_c_hazards.py",
    "test_c_nv.py",
    "test_c_session.py",
    "test_c_supervisor.py",
    "test_c_node.py",
    "test_c_sidebyside.py",
    "test_c_witnessed.py",
    "test_c_witness.py",
    "test_c_gateway_nv.py",
    "test_c_gateway_down_auth.py",
    "test_c_gateway_joins.py",
    "test_gateway_cores.py",
]


def asan_runtime() -> str:
    """Build the ASan module (here: the child loads it, and its compiler then runs without the
    runtime preloaded); the runtime library to preload for it (the compiler's own)."""
    compiled("asan")
    runtime = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE), "--no-print-directory", "asan-runtime"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    if not Path(runtime).is_file():
        pytest.fail(
            f"no ASan runtime found ({runtime!r}): gcc's libasan comes with build-essential",
            pytrace=False,
        )
    return runtime


@pytest.mark.skipif(
    os.environ.get("CANERGY_C_SANITIZER") == "asan", reason="already the ASan child"
)
def test_the_c_tests_pass_under_address_sanitizer() -> None:
    runtime = asan_runtime()
    env = {
        **os.environ,
        "LD_PRELOAD": runtime,
        "ASAN_OPTIONS": "detect_leaks=0:abort_on_error=1",
        "UBSAN_OPTIONS": "print_stacktrace=1:halt_on_error=1",
        "CANERGY_C_SANITIZER": "asan",
        "CANERGY_SIDE_BY_SIDE_EXAMPLES": "60",
    }
    child = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "-x",
            *(str(TESTS / name) for name in UNDER_ASAN),
        ],
        cwd=TESTS.parent,
        env=env,
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
    )
    output = child.stdout + child.stderr
    assert "Sanitizer" not in output and "runtime error" not in output, output[-6000:]
    assert child.returncode == 0, output[-6000:]
    assert " passed" in output and " failed" not in output, output[-3000:]


PROBE = """
import sys
from cffi import FFI
sys.path.insert(0, "tests")
from support.c_binding import RxFrame, library
c = FFI()
c.cdef("void *malloc(size_t);")
libc = c.dlopen(None)
two = libc.malloc(2)  # an ACK needs 3 bytes: the decoder reads one past the end
lib = library()
frame = RxFrame(0x0CE00905, lib.ffi.cast("uint8_t *", int(c.cast("uintptr_t", two))), 3, True)
lib.canergy_decode(0x0CE00000, frame, 0, lib.ffi.NULL)
print("no report")
"""


@pytest.mark.skipif(
    os.environ.get("CANERGY_C_SANITIZER") == "asan", reason="already the ASan child"
)
def test_a_sanitizer_report_fails_the_child() -> None:
    """The set-up above can see a fault: a caller lying about a buffer's length makes the
    ASan build report and abort instead of reading on."""
    runtime = asan_runtime()
    env = {
        **os.environ,
        "LD_PRELOAD": runtime,
        "ASAN_OPTIONS": "detect_leaks=0",
        "CANERGY_C_SANITIZER": "asan",
    }
    child = subprocess.run(
        [sys.executable, "-c", PROBE],
        cwd=TESTS.parent,
        env=env,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    assert child.returncode != 0 and "no report" not in child.stdout
    assert "AddressSanitizer: heap-buffer-overflow" in child.stderr
