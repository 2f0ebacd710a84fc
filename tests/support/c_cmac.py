"""The ctypes mirror of the C AES-CMAC's contexts (firmware/include/canergy/cmac.h).

tests/test_c_cmac.py checks their layout against the compiler's and the C MAC and KDF against
Python's; tests/test_c_auth.py embeds ``Cmac`` in the mirror of the authenticated-frame context.
"""

from __future__ import annotations

from ctypes import Structure, c_uint8


class Aes128(Structure):
    _fields_ = [("rk", c_uint8 * 176)]


class Cmac(Structure):
    _fields_ = [("aes", Aes128), ("k1", c_uint8 * 16), ("k2", c_uint8 * 16)]


class CmacStream(Structure):
    _fields_ = [("x", c_uint8 * 16), ("n", c_uint8)]
