"""The C NV record and store against firmware_model/nvstore.py, byte for byte.

A record written by Python's NvStore loads in C and one the C client asked to write loads in
Python; damaged images (torn writes, flipped bits, truncation, erasure, impossible values,
counters across their wrap) are read alike: the same record or none, the same fallback count,
and the next write goes to the same slot with the same counter.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.c_binding import (
    NEVER,
    SLOT,
    CClient,
    NvState,
    Record,
    c_view,
    cbuf,
    library,
    ref,
    struct_bytes,
)
from support.mem_nv import MemNv, write_slot

from canergy.core import Timing
from canergy.core.state import ClientState, Outcome
from canergy.messages import COUNTER_BOUND, Commit
from firmware_model.nvstore import (
    RECORD_SIZE,
    NvStore,
    SimulatedPowerLoss,
    encode_slot,
    pack_record,
)

U32 = 0xFFFF_FFFF
pending = st.just(0) | st.integers(1, 0xFFFF).map(lambda mj: mj * 1000)
records = st.builds(
    ClientState,
    st.just(5),
    usable=st.integers(0, U32),
    credited=st.integers(0, U32).map(lambda mj: mj * 1000),
    spent=st.integers(0, 2**64 - 1),
    last_tx=st.integers(0, COUNTER_BOUND - 1),  # beyond: tests/test_counters_end.py
    outcome=st.sampled_from(list(Outcome)),
    return_seq=st.integers(0, COUNTER_BOUND - 1),
    return_pending=pending,
    credited_unknown=st.booleans(),
)


def c_record(s: ClientState) -> Record:
    v = c_view(s)
    return Record(**{name: v[name] for name in Record.fields})


def c_load(image: bytes) -> NvState:
    state = NvState()
    buf = cbuf(image, max(len(image), 1))
    library().canergy_nv_load(buf, len(image), ref(state))
    return state


def assert_same_load(image: bytes) -> None:
    """C and Python read ``image`` alike, and put the next record in the same place."""
    raw = bytearray(image)
    store = MemNv(raw)
    loaded = store.load()
    c = c_load(image)
    assert c.fallbacks == store.stats.fallbacks
    assert c.books == (loaded is not None)
    if loaded is not None:
        assert struct_bytes(c.record) == struct_bytes(c_record(loaded))
    assert (c.counter, c.newest_slot) == (store._counter, store._newest_slot)


@given(records)
def test_records_pack_alike(s: ClientState) -> None:
    out = cbuf(RECORD_SIZE)
    library().canergy_record_pack(ref(c_record(s)), out)
    assert bytes(out) == pack_record(s)
    back = Record()
    assert library().canergy_record_unpack(out, ref(back)) == 0
    assert struct_bytes(back) == struct_bytes(c_record(s))


@given(records, st.integers(0, U32))
def test_slots_encode_alike(s: ClientState, counter: int) -> None:
    record = pack_record(s)
    out = cbuf(SLOT)
    library().canergy_nv_slot_encode(counter, record, len(record), out)
    assert bytes(out) == encode_slot(counter, record)


@given(st.lists(records, min_size=1, max_size=5))
def test_python_written_stores_load_in_c(states: list[ClientState]) -> None:
    raw = bytearray()
    for s in states:
        _save_again(raw, s)
    assert struct_bytes(c_load(bytes(raw)).record) == struct_bytes(c_record(states[-1]))
    assert_same_load(bytes(raw))


def _save_again(raw: bytearray, s: ClientState) -> None:
    """A save after a reboot: a fresh store that reads the image first, as a node does."""
    store = MemNv(raw)
    store.load()
    store.save(s)


@given(st.lists(st.sampled_from(["spend", "give", "commit"]), min_size=1, max_size=8))
def test_c_written_images_load_in_python(steps: list[str]) -> None:
    """The C client's own persist requests, written where it says, are Python's records."""
    c = CClient(5, timing=Timing(), state=ClientState(5, usable=9_000_000, credited=9_000_000))
    c.nv = bytearray()
    tx = 1
    for step in steps:
        if step == "spend":
            c.do_spend(1234)
        elif step == "give" and c.can_give_back():
            c.do_give_back(1000, 0)
        else:
            c.message(Commit(5, tx, 7), 0)
            tx += 1
        if c.out.persist:
            write_slot(c.nv, c.out.nv_slot, bytes(c.out.nv_image))
    if c.nv:
        record = MemNv(c.nv).load()
        assert record is not None and c_view(record) == {
            **c_view(c.state),
            "phase": 0,
            "held_tx": 0,
            "held_amount_mj": 0,
            "nonce": 0,
            "deadline": NEVER,
            "return_deadline": NEVER,
        }


@given(
    st.lists(records, min_size=1, max_size=6),
    st.integers(1, 6),
)
def test_torn_writes_fall_back_alike(states: list[ClientState], tear_at: int) -> None:
    raw = bytearray()
    store = MemNv(raw)
    store.crash_after = tear_at
    try:
        for s in states:
            store.save(s)
    except SimulatedPowerLoss:
        pass
    assert_same_load(bytes(raw))


@given(
    st.lists(records, min_size=1, max_size=4),
    st.lists(st.tuples(st.integers(0, 2 * SLOT - 1), st.integers(1, 255)), max_size=3),
    st.none() | st.integers(0, 2 * SLOT + 10),
    st.none() | st.sampled_from([0, 1]),
)
def test_damaged_images_load_alike(
    states: list[ClientState],
    flips: list[tuple[int, int]],
    truncate: int | None,
    erase: int | None,
) -> None:
    raw = bytearray()
    for s in states:
        _save_again(raw, s)
    for at, mask in flips:
        raw[at % len(raw)] ^= mask
    if erase is not None:
        raw[erase * SLOT : (erase + 1) * SLOT] = bytes(SLOT)
    if truncate is not None:
        del raw[truncate:]
    assert_same_load(bytes(raw))


@given(st.integers(0, U32), st.integers(0, U32), records, records)
def test_counters_compare_as_serial_numbers_alike(
    c0: int, c1: int, a: ClientState, b: ClientState
) -> None:
    image = encode_slot(c0, pack_record(a)) + encode_slot(c1, pack_record(b))
    assert_same_load(image)


@pytest.mark.parametrize(
    "c0, c1",
    [(U32, 0), (0, U32), (5, 5), (0x7FFFFFFF, 0x80000000), (0, 0x80000000), (0x80000000, 0)],
)
def test_counter_wrap_edges(c0: int, c1: int) -> None:
    a, b = ClientState(5, usable=1000), ClientState(5, usable=2000)
    assert_same_load(encode_slot(c0, pack_record(a)) + encode_slot(c1, pack_record(b)))


@pytest.mark.parametrize("outcome", [5, 9, 255])
def test_impossible_outcomes_are_no_books_alike(outcome: int) -> None:
    record = bytearray(pack_record(ClientState(5, usable=5000)))
    record[28] = outcome
    image = encode_slot(1, bytes(record)) + bytes(SLOT)
    assert_same_load(image)
    assert not c_load(image).books and c_load(image).fallbacks == 1


@pytest.mark.parametrize("pending_uj", [1, 999, 1500, 65_536_000, U32])
def test_impossible_pending_returns_are_no_books_in_both(pending_uj: int) -> None:
    """A pending return no client can have sent (not whole mJ, or more than a frame): both loads
    refuse the record (no books) rather than fail later when re-sending it."""
    image = encode_slot(1, pack_record(ClientState(5, return_pending=pending_uj)))
    c = c_load(image + bytes(SLOT))
    assert not c.books and c.fallbacks == 1
    assert MemNv(bytearray(image)).load() is None


def test_the_parameter_slot_survives_c_writes(tmp_path: Path) -> None:
    """firmware_model keeps CANopen parameters in slot 2 (offset 80); the C client's writes go
    to slots 0 and 1 only, so the parameters stay readable."""
    path = tmp_path / "node.nv"
    store = NvStore(path, 5, fsync=False)
    store.save(ClientState(5, usable=20_000, credited=20_000))
    store.save_params((100, 500, 1000, 0b111))
    image = bytearray(path.read_bytes())
    c = CClient(5, timing=Timing())
    c.start(bytes(image), 0, 0)
    for _ in range(3):
        c.do_spend(1000)
        write_slot(image, c.out.nv_slot, bytes(c.out.nv_image))
    path.write_bytes(bytes(image))
    again = NvStore(path, 5)
    assert again.load_params() == (100, 500, 1000, 0b111)
    loaded = again.load()
    assert loaded is not None and loaded.usable == 17_000 and loaded.spent == 3000
