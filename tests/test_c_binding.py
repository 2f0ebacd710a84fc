"""The ctypes mirror of the C client library (``support.c_binding``) matches what the compiler
laid out, field by field and struct by struct, and the C test program passes."""

from __future__ import annotations

import ctypes

import pytest
from support.c_binding import MIRROR, CClientState, CNodeState, library, make


@pytest.mark.parametrize("name", sorted(MIRROR))
def test_the_ctypes_mirror_matches_the_compiled_layout(name: str) -> None:
    lib = library()
    struct = MIRROR[name]
    assert lib.canergy_test_sizeof(name.encode()) == ctypes.sizeof(struct)
    for field, *_ in struct._fields_:
        offset = lib.canergy_test_offset(f"{name}.{field}".encode())
        assert offset == getattr(struct, field).offset, f"{name}.{field}"


def test_state_fits_the_budget() -> None:
    assert ctypes.sizeof(CClientState) <= 128 and ctypes.sizeof(CNodeState) <= 128


def test_the_c_test_program_passes() -> None:
    make("test")
