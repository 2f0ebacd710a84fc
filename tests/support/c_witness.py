"""The C witness and gateway policy (firmware/include/canergy/witness.h, gateway.h's top-up and
give-back) seen from Python, on the library ``support.c_binding`` builds: the structs as the
headers declare them (cffi), the flags and verdicts read from the binding."""

from __future__ import annotations

from typing import Any

from support.c_binding import Struct, library

CWitness = Struct("witness")
CRelease = Struct("witness_release")
CGatewayNv = Struct("gateway_nv")


def _constant(name: str) -> Any:
    return getattr(library(), name)


def __getattr__(name: str) -> Any:
    """``SLOTS``, the findings (``SAW``...), the verdicts (``OLD``...), ``GW_NV_SLOT``: the
    binding's values of the headers' names."""
    renamed = {
        "SLOTS": "CANERGY_WITNESS_SLOTS",
        "GW_NV_SLOT": "CANERGY_GW_NV_SLOT_SIZE",
        "SAW": "CANERGY_WITNESS_SAW",
        "WENT_BACK": "CANERGY_WITNESS_WENT_BACK",
        "SINCE_START": "CANERGY_WITNESS_SINCE_START",
        "RESTARTED": "CANERGY_WITNESS_RESTARTED",
        "OLD": "CANERGY_WITNESS_OLD",
        "HELD": "CANERGY_WITNESS_HELD",
        "CONTRADICTED": "CANERGY_WITNESS_CONTRADICTED",
        "FULL": "CANERGY_WITNESS_FULL",
    }
    if name not in renamed:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return _constant(renamed[name])


def policy_library() -> Any:
    """``support.c_binding.library()``: every declared function is in it."""
    return library()
