"""The client's NV record and A/B store: layout, round trip, torn and corrupted writes."""

from __future__ import annotations

import gc
import struct
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from canergy.core.state import ClientState, Outcome
from canergy.messages import COUNTER_BOUND, USABLE_MAX_UJ
from canergy.seqnum import unwrap
from firmware_model.nvstore import (
    RECORD_SIZE,
    SLOT_SIZE,
    NvError,
    NvStore,
    SimulatedPowerLoss,
    encode_slot,
    pack_record,
    unpack_record,
)

u32 = st.integers(0, 0xFFFFFFFF)
counters = st.integers(0, COUNTER_BOUND - 1)  # beyond: tests/test_counters_end.py
records = st.builds(
    ClientState,
    st.just(5),
    usable=u32,
    credited=u32.map(lambda mj: mj * 1000),
    spent=st.integers(0, 2**64 - 1),
    last_tx=counters,
    outcome=st.sampled_from(list(Outcome)),
    return_seq=counters,
    return_pending=st.integers(0, 0xFFFF).map(lambda mj: mj * 1000),  # one frame, whole mJ
    credited_unknown=st.booleans(),
)


def test_the_record_fits_32_bytes() -> None:
    assert RECORD_SIZE <= 32 and len(pack_record(ClientState(1))) == RECORD_SIZE


@given(records)
def test_persistent_fields_round_trip(c: ClientState) -> None:
    assert unpack_record(5, pack_record(c)) == c


def test_values_that_do_not_fit_are_refused() -> None:
    with pytest.raises(NvError):
        pack_record(ClientState(1, usable=2**32))
    with pytest.raises(NvError):
        pack_record(ClientState(1, credited=1500))  # not whole quanta


def _states(n: int) -> list[ClientState]:
    return [
        ClientState(3, usable=1000 * (10 - i), credited=10_000, spent=1000 * i) for i in range(n)
    ]


def test_the_newest_complete_write_wins(tmp_path: Path) -> None:
    store = NvStore(tmp_path / "n.nv", 3, fsync=False)
    assert store.load() is None  # no file: no books (the node must JOIN)
    for s in _states(5):
        store.save(s)
    reopened = NvStore(tmp_path / "n.nv", 3, fsync=False)
    assert reopened.load() == _states(5)[-1]
    reopened.save(_states(6)[-1])  # continues the counter, alternating slots
    assert NvStore(tmp_path / "n.nv", 3).load() == _states(6)[-1]


@pytest.mark.parametrize("writes", [1, 2, 3, 6])
def test_a_torn_write_falls_back_to_the_previous_record(tmp_path: Path, writes: int) -> None:
    store = NvStore(tmp_path / "n.nv", 3, fsync=False, crash_after=writes)
    states = _states(writes)
    with pytest.raises(SimulatedPowerLoss):
        for s in states:
            store.save(s)
    after = NvStore(tmp_path / "n.nv", 3)
    expected = states[-2] if writes > 1 else None  # the first write torn: still no books
    assert after.load() == expected
    assert after.stats.fallbacks == 1


@pytest.mark.parametrize("damage", ["flip", "truncate", "zero"])
def test_damage_to_the_newest_slot_never_yields_more_than_the_older_record(
    tmp_path: Path, damage: str
) -> None:
    path = tmp_path / "n.nv"
    store = NvStore(path, 3, fsync=False)
    older, newer = _states(2)
    store.save(older)
    store.save(newer)  # slot 1
    raw = bytearray(path.read_bytes())
    if damage == "flip":
        raw[SLOT_SIZE + 10] ^= 0x40
    elif damage == "zero":
        raw[SLOT_SIZE:] = bytes(SLOT_SIZE)
    else:
        raw = raw[: SLOT_SIZE + 7]
    path.write_bytes(bytes(raw))
    assert NvStore(path, 3).load() == older


def test_garbage_in_both_slots_is_no_books(tmp_path: Path) -> None:
    path = tmp_path / "n.nv"
    path.write_bytes(b"\xa5" * (2 * SLOT_SIZE))
    store = NvStore(path, 3)
    assert store.load() is None and store.stats.fallbacks == 1


@pytest.mark.parametrize(
    "state",
    [
        ClientState(3, usable=5000, outcome=9),  # type: ignore[arg-type]  # no such outcome
        ClientState(3, return_seq=1, return_pending=1500),  # not whole mJ: no client returns it
        ClientState(3, return_seq=1, return_pending=66_000_000),  # more than one frame carries
    ],
)
def test_a_valid_slot_with_impossible_values_is_no_books(
    tmp_path: Path, state: ClientState
) -> None:
    """A CRC collision over garbage must not crash the node at start (NvError) nor be trusted."""
    path = tmp_path / "n.nv"
    record = struct.pack(
        "<IIQIIIBB",
        state.usable,
        0,
        0,
        0,
        state.return_seq,
        state.return_pending,
        int(state.outcome),
        0,
    )
    path.write_bytes(encode_slot(1, record) + bytes(SLOT_SIZE))
    store = NvStore(path, 3)
    assert store.load() is None and store.stats.fallbacks == 1


def test_counters_are_kept_modulo_2_32_and_compare_the_same(tmp_path: Path) -> None:
    """Rc, ltx and the return number grow without bound; the record keeps them modulo 2**32,
    which the wire's 24- and 16-bit serial comparisons cannot tell apart."""
    big = ClientState(
        3,
        usable=USABLE_MAX_UJ,
        credited=(2**32 + 7) * 1000,
        last_tx=2**32 + 5,
        return_seq=2**33 + 2,
        outcome=Outcome.COMMITTED,
    )
    store = NvStore(tmp_path / "n.nv", 3, fsync=False)
    store.save(big)
    back = store.load()
    assert back is not None
    assert (back.credited, back.last_tx, back.return_seq) == (7000, 5, 2)
    assert back.usable == USABLE_MAX_UJ
    for wire in (0, 5, 6, 0x8000, 0xFFFF):  # every tx comparison comes out the same
        assert (
            unwrap(wire, back.last_tx, 16) - back.last_tx
            == unwrap(wire, big.last_tx, 16) - big.last_tx
        )


def test_admitted_without_books_survives_a_restart(tmp_path: Path) -> None:
    state = ClientState(3, last_tx=40, outcome=Outcome.SETTLED, credited_unknown=True)
    store = NvStore(tmp_path / "n.nv", 3, fsync=False)
    store.save(state)
    assert NvStore(tmp_path / "n.nv", 3).load() == state


@pytest.mark.parametrize("start", [0xFFFF_FFFD, 0xFFFF_FFFE, 0xFFFF_FFFF, 0x7FFF_FFFF])
def test_slot_counters_compare_across_the_32_bit_wrap(tmp_path: Path, start: int) -> None:
    """Regression: after 2**32 writes the older slot won (usable 1 J became 5 J)."""
    store = NvStore(tmp_path / "n.nv", 3, fsync=False)
    store._counter = start  # as if this many writes had happened
    states = _states(4)
    for written, s in enumerate(states, 1):
        store.save(s)
        assert NvStore(tmp_path / "n.nv", 3, fsync=False).load() == s, written
    reopened = NvStore(tmp_path / "n.nv", 3, fsync=False)
    reopened.load()
    reopened.save(states[0])
    assert NvStore(tmp_path / "n.nv", 3, fsync=False).load() == states[0]


def _open_under(folder: Path) -> int:
    """How many of this process's descriptors are open on files under ``folder``."""
    targets = []
    for fd in Path("/proc/self/fd").iterdir():
        try:
            targets.append(fd.readlink())
        except OSError:  # closed meanwhile (the listing's own descriptor)
            continue
    return sum(folder in target.parents for target in targets)


def test_a_store_keeps_one_file_open_and_closes_it(tmp_path: Path) -> None:
    """Writes go through one descriptor kept open (a flash driver set up once); it is closed by
    ``close`` or when the store is dropped, so nodes started and stopped leak none."""
    store = NvStore(tmp_path / "kept.nv", 3, fsync=False)
    for state in _states(4):
        store.save(state)
    assert _open_under(tmp_path) == 1
    store.close()
    assert _open_under(tmp_path) == 0
    assert NvStore(tmp_path / "kept.nv", 3).load() == _states(4)[-1]
    for i in range(50):  # dropped without close
        NvStore(tmp_path / f"{i}.nv", 3, fsync=False).save(_states(1)[0])
    gc.collect()
    assert _open_under(tmp_path) == 0
