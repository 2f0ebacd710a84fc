"""The C witness and gateway policy (firmware/include/canergy/witness.h, gateway.h's top-up and
give-back) seen from Python: a ctypes mirror of their structs and signatures, on the library
``support.c_binding`` loads. Kept apart from that module's mirror (issue 41: the binding moves
to cffi); tests/test_c_witness.py checks the layout against the compiler's."""

from __future__ import annotations

import ctypes
from ctypes import (
    POINTER,
    Structure,
    c_bool,
    c_int,
    c_int64,
    c_uint,
    c_uint8,
    c_uint16,
    c_uint32,
    c_uint64,
)

from support.c_binding import SUPERVISOR_NODES, CGateway, CSession, Msg, Record, library

SLOTS = 4
"""CANERGY_WITNESS_SLOTS: return numbers held at once per node."""
SAW, WENT_BACK, SINCE_START, RESTARTED = 0x01, 0x02, 0x04, 0x08
OLD, HELD, CONTRADICTED, FULL = 0, 1, 2, 3


class CHeld(Structure):
    _fields_ = [
        ("seq", c_int64),
        ("confirmed_at", c_uint64),
        ("amount_mj", c_uint16),
        ("confirmed", c_bool),
    ]


class CWitness(Structure):
    _fields_ = [
        ("held", CHeld * SLOTS),
        ("resume_held", CHeld),
        ("resume", Msg),
        ("return_seq", c_int64),
        ("confirmed_at", c_uint64),
        ("evidence_at", c_uint64),
        ("refuted", c_uint32),
        ("resynced", c_uint32),
        ("resume_nonce", c_uint16),
        ("witness", c_uint8),
        ("held_count", c_uint8),
        ("has_witness", c_bool),
        ("has_return_seq", c_bool),
        ("has_evidence", c_bool),
        ("has_resume", c_bool),
        ("has_resume_nonce", c_bool),
    ]


class CReleased(Structure):
    _fields_ = [("first_missed", c_int64), ("seq", c_int64), ("amount_mj", c_uint16)]


class CRelease(Structure):
    _fields_ = [
        ("returns", CReleased * SLOTS),
        ("resume_msg", Msg),
        ("count", c_uint8),
        ("resume", c_bool),
    ]


class CGatewayNv(Structure):
    _fields_ = [
        ("up", Record),
        ("down", ctypes.c_void_p),
        ("counter", c_uint32),
        ("slot", ctypes.c_int8),
        ("older", c_uint8),
        ("foreign", c_bool),
    ]


GW_NV_SLOT = 8 + 30 + 40 + 44 * SUPERVISOR_NODES + 4
"""CANERGY_GW_NV_SLOT_SIZE of the test library's build."""

MIRROR = {
    "canergy_gateway_nv": CGatewayNv,
    "canergy_held": CHeld,
    "canergy_witness": CWitness,
    "canergy_witness_release": CRelease,
}

_W, _M = POINTER(CWitness), POINTER(Msg)
_SIGNATURES = {
    "canergy_witness_init": (None, [_W]),
    "canergy_witness_telemetry": (c_uint, [_W, _M, c_uint32, c_uint64]),
    "canergy_witness_hold": (c_int, [_W, _M, c_uint32, c_uint64]),
    "canergy_witness_hold_resume": (c_bool, [_W, _M, c_uint32, c_uint64, c_bool]),
    "canergy_witness_release": (None, [_W, c_uint32, c_uint64, c_uint64, POINTER(CRelease)]),
    "canergy_witness_release_at": (c_bool, [POINTER(CRelease), c_uint8, c_uint32, _M]),
    "canergy_witness_refute": (None, [_W, c_uint64]),
    "canergy_witness_blocked": (c_bool, [_W, c_uint64, c_uint64]),
    "canergy_witness_readmitted": (None, [_W]),
    "canergy_witness_next_release": (c_uint64, [_W, c_uint64]),
    "canergy_witness_beyond_books": (c_bool, [POINTER(CSession), _M]),
    "canergy_gateway_nv_encode": (None, [POINTER(CGateway), c_uint32, ctypes.c_char_p]),
    "canergy_gateway_nv_load": (c_int, [ctypes.c_char_p, ctypes.c_size_t, POINTER(CGatewayNv)]),
    "canergy_gateway_top_up": (c_uint32, [c_uint64, c_uint64, c_uint64, c_int64]),
    "canergy_gateway_give_back_amount": (c_uint32, [c_int64, c_uint64]),
}


def policy_library() -> ctypes.CDLL:
    """``support.c_binding.library()`` with the witness's and the gateway policy's signatures."""
    lib = library()
    for fn, (restype, argtypes) in _SIGNATURES.items():
        f = getattr(lib, fn)
        f.restype, f.argtypes = restype, argtypes
    return lib
