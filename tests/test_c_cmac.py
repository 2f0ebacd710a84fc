"""The C AES-CMAC and KDF (firmware/include/canergy/cmac.h) against Python's ``cryptography``:
any key and message give the same MAC, one-shot and in pieces; the KDF gives the same key as
``KBKDFCMAC`` in counter mode (32-bit counter before the fixed input, 32-bit L) and is exactly
the byte layout the header documents; truncated MACs compare as bytes do."""

from __future__ import annotations

import itertools
from typing import Any

from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC
from cryptography.hazmat.primitives.kdf.kbkdf import KBKDFCMAC, CounterLocation, Mode
from hypothesis import example, given
from hypothesis import strategies as st
from support.c_binding import CLib, Struct, cbuf, library, ref, struct_bytes

RFC4493_KEY = bytes.fromhex("2b7e151628aed2a6abf7158809cf4f3c")
keys = st.binary(min_size=16, max_size=16)
messages = st.binary(max_size=100)
Cmac, CmacStream = Struct("cmac"), Struct("cmac_stream")


def lib() -> CLib:
    return library()


def c_key(key: bytes) -> Any:
    ctx = Cmac()
    lib().canergy_cmac_init(ref(ctx), key)
    return ctx


def c_cmac(key: bytes, msg: bytes) -> bytes:
    mac = cbuf(16)
    lib().canergy_cmac(ref(c_key(key)), msg, len(msg), mac)
    return bytes(mac)


def py_cmac(key: bytes, msg: bytes) -> bytes:
    c = CMAC(algorithms.AES(key))
    c.update(msg)
    return c.finalize()


def c_kdf(master: bytes, label: bytes, context: bytes) -> bytes:
    out = cbuf(16)
    lib().canergy_kdf_cmac_ctr(master, label, len(label), context, len(context), out)
    return bytes(out)


def py_kdf(master: bytes, label: bytes, context: bytes) -> bytes:
    return KBKDFCMAC(
        algorithm=algorithms.AES,
        mode=Mode.CounterMode,
        length=16,
        rlen=4,
        llen=4,
        location=CounterLocation.BeforeFixed,
        label=label,
        context=context,
        fixed=None,
    ).derive(master)


def c_equal(a: bytes, b: bytes, n: int) -> bool:
    return bool(lib().canergy_mac_equal(a, b, n))


def test_rfc4493_subkeys() -> None:
    ctx = c_key(RFC4493_KEY)
    assert bytes(ctx.k1).hex() == "fbeed618357133667c85e08f7236a8de"
    assert bytes(ctx.k2).hex() == "f7ddac306ae266ccf90bc11ee46d513b"


@given(keys, messages)
@example(RFC4493_KEY, b"")
@example(bytes(16), bytes(16))
@example(b"\xff" * 16, b"\xff" * 32)
def test_cmac_matches_cryptography(key: bytes, msg: bytes) -> None:
    assert c_cmac(key, msg) == py_cmac(key, msg)


@given(keys, messages, st.lists(st.integers(0, 100), max_size=6))
def test_cmac_in_pieces_is_the_one_shot_mac(key: bytes, msg: bytes, cuts: list[int]) -> None:
    ctx, s, mac = c_key(key), CmacStream(), cbuf(16)
    lib().canergy_cmac_begin(ref(s))
    bounds = [0, *sorted(min(c, len(msg)) for c in cuts), len(msg)]
    for lo, hi in itertools.pairwise(bounds):
        lib().canergy_cmac_update(ref(ctx), ref(s), msg[lo:hi], hi - lo)
    lib().canergy_cmac_final(ref(ctx), ref(s), mac)
    assert bytes(mac) == py_cmac(key, msg)
    assert struct_bytes(s) == bytes(CmacStream.size()), "final wipes the stream"


@given(keys, st.binary(max_size=40), st.binary(max_size=40))
@example(RFC4493_KEY, b"canergy node key", b"\x05")
@example(RFC4493_KEY, b"", b"")
def test_kdf_matches_kbkdfcmac_and_the_documented_layout(
    master: bytes, label: bytes, context: bytes
) -> None:
    derived = c_kdf(master, label, context)
    assert derived == py_kdf(master, label, context)
    layout = b"\x00\x00\x00\x01" + label + b"\x00" + context + b"\x00\x00\x00\x80"
    assert derived == py_cmac(master, layout)


def test_kdf_known_answer_of_the_c_tests() -> None:
    expected = "e169cefb0c726e0e1bf3d23ae4116882"  # also in firmware/tests/test_vectors.c
    assert py_kdf(RFC4493_KEY, b"canergy node key", b"\x05").hex() == expected
    assert c_kdf(RFC4493_KEY, b"canergy node key", b"\x05").hex() == expected


@given(keys, messages, st.integers(1, 16), st.binary(min_size=16, max_size=16))
def test_truncated_macs_compare_as_bytes(key: bytes, msg: bytes, n: int, received: bytes) -> None:
    mac = c_cmac(key, msg)
    assert c_equal(mac, mac[0:n] + received[n:], n)
    assert c_equal(mac, received, n) == (mac[0:n] == received[0:n])
    flipped = bytearray(mac)
    flipped[n - 1] ^= 0x80
    assert not c_equal(mac, bytes(flipped), n)
    assert not c_equal(mac, mac, 0), "a MAC of no bytes never matches"


def test_wiping() -> None:
    ctx = c_key(RFC4493_KEY)
    assert any(struct_bytes(ctx))
    lib().canergy_cmac_wipe(ref(ctx))
    assert struct_bytes(ctx) == bytes(Cmac.size())
    buf = cbuf(bytes([1, 2, 3, 4, 5]))
    lib().canergy_wipe(buf + 1, 3)
    assert list(buf) == [1, 0, 0, 0, 5]
