"""The gateway's NV slot in the library (``canergy_gateway_nv_encode`` and ``_load``,
firmware/src/nv.c): both roles' books in one slot, the newest of two valid slots taken in
serial order, a damaged one passed over, a record beyond the counter bound refusing both slots,
an older layout and a file that is not a gateway's told apart. (The ports' refusals built on it:
tests/test_counters_end.py, tests/test_c_witnessed.py.)"""

from __future__ import annotations

import struct
import zlib

import pytest
from support.c_binding import ERR_END, OK, CGateway, cbuf, struct_bytes
from support.c_witness import GW_NV_SLOT, CGatewayNv, policy_library

from canergy.core.common import COUNTER_BOUND

SUP_AT = 8 + 30  # the supervisor's slot image within a gateway slot


def _slot(counter: int, usable: int = 0, last_tx: int = 0) -> bytes:
    gw = CGateway()
    gw.up.rec.usable_uj, gw.up.rec.last_tx = usable, last_tx
    out = cbuf(GW_NV_SLOT)
    policy_library().canergy_gateway_nv_encode(gw, counter, out)
    return struct_bytes(out)


def _load(image: bytes) -> tuple[int, CGatewayNv]:
    nv = CGatewayNv()
    rc = policy_library().canergy_gateway_nv_load(cbuf(image), len(image), nv)
    return rc, nv


def _resealed(slot: bytes) -> bytes:
    return slot[:-4] + struct.pack("<I", zlib.crc32(slot[:-4]))


@pytest.mark.parametrize(
    ("first", "second", "newest"),
    [(5, 6, 1), (6, 5, 0), (2**32 - 1, 0, 1), (0, 2**32 - 1, 0), (7, 7, 0)],
)
def test_the_newest_slot_is_taken_in_serial_order(first: int, second: int, newest: int) -> None:
    rc, nv = _load(_slot(first, usable=1_000) + _slot(second, usable=2_000))
    assert (rc, nv.slot, nv.up.usable_uj) == (OK, newest, 1_000 * (newest + 1))
    assert nv.counter == (first, second)[newest] and not nv.foreign and nv.older == 0


def test_a_damaged_newest_slot_falls_back_to_the_older() -> None:
    newer = bytearray(_slot(9, usable=2_000))
    newer[SUP_AT - 5] ^= 0x01  # a bit of its record: the CRC fails
    rc, nv = _load(_slot(8, usable=1_000) + bytes(newer))
    assert (rc, nv.slot, nv.counter, nv.up.usable_uj) == (OK, 0, 8, 1_000)
    assert nv.damaged == 0b10  # the port says so, and takes the older


def test_damaged_and_cut_short_slots_are_named_blank_ones_are_not() -> None:
    """``damaged``: the slots that start as one does (the magic) but do not hold (the CRC, or cut
    short): the port refuses a file with such a slot and no valid one."""
    older, newer = _slot(8), bytearray(_slot(9))
    newer[SUP_AT + 10] ^= 0x80
    assert _load(older + bytes(newer))[1].damaged == 0b10
    edited = bytearray(older)
    edited[20] ^= 0x02
    rc, nv = _load(bytes(edited) + bytes(newer))
    assert (rc, nv.slot, nv.damaged) == (OK, -1, 0b11)
    assert _load(older[: GW_NV_SLOT // 2])[1].damaged == 0b01  # cut within the first slot
    assert _load(older + _slot(9)[:100])[1].damaged == 0b10  # the second's write cut short
    assert _load(older)[1].damaged == 0 and _load(bytes(2 * GW_NV_SLOT))[1].damaged == 0
    assert _load(b"")[1].damaged == 0


def test_a_record_beyond_the_bound_refuses_both_slots() -> None:
    rc, nv = _load(_slot(8) + _slot(9, last_tx=COUNTER_BOUND))
    assert (rc, nv.slot, nv.up.last_tx) == (ERR_END, -1, COUNTER_BOUND)


def test_no_books_an_older_layout_and_a_nodes_file_are_told_apart() -> None:
    assert _load(b"")[1].slot == -1 and not _load(b"")[1].foreign
    assert _load(bytes(2 * GW_NV_SLOT))[1].slot == -1
    node_file = struct.pack("<HI", 0xCE57, 1) + bytes(34)
    assert _load(node_file)[1].foreign
    v3 = bytearray(_slot(3))
    v3[SUP_AT + 4] = 3  # the supervisor record's version
    rc, nv = _load(_resealed(bytes(v3)) + bytes(GW_NV_SLOT))
    assert (rc, nv.older) == (OK, 3)


@pytest.mark.parametrize("version", [3, 4])
def test_a_slot_of_the_44_byte_layout_is_told_as_older(version: int) -> None:
    """Versions 3 and 4 of the supervisor record held 44 bytes per node (version 5 keeps the last
    JOIN admitted: 56): a gateway slot of that size and version is an older layout, named."""
    nodes = (GW_NV_SLOT - SUP_AT - 40 - 4) // 56
    head = struct.pack("<IBBBBIQQQ", 0x534E5243, version, 0, 0, 0, 1, 0, 0, 0)
    below = (head + b"\0" * 4).ljust(40 + 44 * nodes, b"\0")
    rc, nv = _load(_resealed(_slot(3)[:SUP_AT] + below + bytes(4)))
    assert (rc, nv.older, nv.slot) == (OK, version, -1)
