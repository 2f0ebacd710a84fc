"""The binding's declarations are the headers': cffi is handed what the preprocessor reads in
firmware/include/canergy/*.h (no copy to drift), and the C test program passes."""

from __future__ import annotations

import shutil
from pathlib import Path

from support.c_binding import CClientState, CNodeState, library, make

from canergy.ccore.build import declarations


def test_a_header_change_reaches_the_binding(tmp_path: Path) -> None:
    """A field and a constant added to a header appear in the declarations, unedited."""
    root = Path(__file__).resolve().parents[1]
    shutil.copytree(root / "firmware" / "include", tmp_path / "firmware" / "include")
    header = tmp_path / "firmware" / "include" / "canergy" / "codec.h"
    text = header.read_text()
    text = text.replace(
        "struct canergy_msg {", "struct canergy_msg {\n    uint32_t probe_field;", 1
    )
    header.write_text(
        text.replace("#define CANERGY_OK 0", "#define CANERGY_OK 0\n#define CANERGY_PROBE 7")
    )
    before, after = declarations(root), declarations(tmp_path)
    assert "probe_field" not in before and "uint32_t probe_field;" in after
    assert "#define CANERGY_PROBE ..." in after
    assert set(before.splitlines()) <= set(after.splitlines())


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
