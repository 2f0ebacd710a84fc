"""The binding's declarations are the headers': cffi is handed what the preprocessor reads in
firmware/include/canergy/*.h (no copy to drift), and the C test program passes."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from support.c_binding import (
    SANITIZER,
    CClientState,
    CNodeState,
    compiled_core,
    library,
    make,
)

from canergy.auth.frames import AuthFailure
from canergy.ccore.build import declarations, fingerprint, load


def test_a_header_change_reaches_the_binding(tmp_path: Path) -> None:
    """A field and a constant added to a header appear in the declarations, unedited."""
    root = Path(__file__).resolve().parents[1]
    shutil.copytree(root / "firmware" / "include", tmp_path / "firmware" / "include")
    header = tmp_path / "firmware" / "include" / "canergy" / "codec.h"
    text = header.read_text()
    text = text.replace(
        "struct canergy_msg {", "struct canergy_msg {\n    uint32_t probe_field;", 1
    )
    header.write_text(text.replace("#define CANERGY_MAX_NODE 127U", "#define CANERGY_PROBE 7", 1))
    before, after = declarations(root), declarations(tmp_path)
    assert "probe_field" not in before and "uint32_t probe_field;" in after
    assert "#define CANERGY_PROBE ..." in after and "#define CANERGY_PROBE ..." not in before
    assert "#define CANERGY_MAX_NODE ..." in before and "#define CANERGY_MAX_NODE ..." not in after


def test_a_changed_source_is_built_again(tmp_path: Path) -> None:
    """The tests' builds are kept per digest of what they are built from: a byte changed in a
    C source, a header or the Makefile (whose SRCS the extension compiles) names another
    build, so a stale one is never loaded."""
    root = Path(__file__).resolve().parents[1]
    for part in ("src", "include"):
        shutil.copytree(root / "firmware" / part, tmp_path / "firmware" / part)
    shutil.copy2(root / "firmware" / "Makefile", tmp_path / "firmware" / "Makefile")
    assert fingerprint(tmp_path, "ubsan") == fingerprint(root, "ubsan")
    seen = {fingerprint(root, "ubsan"), fingerprint(root, "broken")}
    for changed in ("src/session.c", "include/canergy/status.h", "Makefile"):
        path = tmp_path / "firmware" / changed
        text = path.read_text()
        path.write_text(text + "\n")
        seen.add(fingerprint(tmp_path, "ubsan"))
        path.write_text(text)
    assert len(seen) == 5


def test_the_tests_drive_the_builders_module() -> None:
    """``library()`` is ``canergy.ccore.build.load``'s module, the one ``CompiledSupervisor``
    runs when handed it."""
    assert library().module is load("asan" if SANITIZER == "asan" else "ubsan")
    assert compiled_core([1], 0)._lib is library().module.lib


def test_every_public_function_is_bound() -> None:
    """Each function the headers declare can be called from the tests' build."""
    lib = library()
    root = Path(__file__).resolve().parents[1] / "firmware" / "include" / "canergy"
    names = {
        word.split("(")[0]
        for h in root.glob("*.h")
        for word in h.read_text().split()
        if word.startswith("canergy_") and "(" in word
    }
    assert len(names) > 50
    assert [n for n in sorted(names) if not callable(getattr(lib, n, None))] == []


def test_state_fits_the_budget() -> None:
    assert CClientState.size() <= 128 and CNodeState.size() <= 128


def test_the_c_test_program_passes() -> None:
    make("test")


INCLUDE = Path(__file__).resolve().parents[1] / "firmware" / "include" / "canergy"
STATUS = re.compile(r"CANERGY_(?:OK|ERR_\w+|DECODE_\w+|RX_\w+)")
VERDICTS = {"CANERGY_AUTH_PENDING"} | {f"CANERGY_AUTH_{f.name}" for f in AuthFailure}
"""The authenticated frames' verdicts (auth.h's other CANERGY_AUTH_* are sizes and layouts)."""


def _defined(text: str) -> set[str]:
    """The status-like names a header defines (a macro or an enumerator)."""
    names = set(re.findall(r"#define (CANERGY_\w+)", text))
    names |= set(re.findall(r"^\s+(CANERGY_\w+) = ", text, re.M))
    return {n for n in names if STATUS.fullmatch(n) or n in VERDICTS}


def test_status_codes_are_one_family_in_one_header() -> None:
    """Every status code is defined in canergy/status.h, and no two name one value (but
    CANERGY_OK and CANERGY_DECODE_OK, both success): whatever int a call returns reads as one
    outcome. The constants the binding gives Python are these."""
    lib = library()
    in_status = _defined((INCLUDE / "status.h").read_text())
    elsewhere = {
        h.name: _defined(h.read_text()) for h in INCLUDE.glob("*.h") if h.name != "status.h"
    }
    assert {h: names for h, names in elsewhere.items() if names} == {}
    values: dict[int, list[str]] = {}
    for name in sorted(in_status):
        values.setdefault(getattr(lib, name), []).append(name)
    assert {v: n for v, n in values.items() if len(n) > 1} == {
        0: ["CANERGY_DECODE_OK", "CANERGY_OK"]
    }
    assert len(in_status) > 25
