"""Counters at their ends (issue 40, item 7): the bound the theorem assumes (``canergy prove``,
assumption 4: every 32-bit counter below 2**30) is enforced where a record is loaded and where a
counter moves, alike in the Python and the C core.

- Loading: a supervisor state file, the emulator's and the C node's NV file, the C gateway's NV
  file (either role) holding a transaction or return number at or beyond 2**30 is refused, with
  the field named; 2**30 - 1 loads.
- Moving: no rule takes a counter to ``COUNTER_END`` (2**30 - 2**16) or beyond: the supervisor
  begins no transaction and credits no return numbered there, an admission's lift stays below
  it. The client's side (no intention, commit or return numbered there) is compared cell by cell
  in tests/test_c_hardened.py, from records up to 2**30 - 1.
"""

from __future__ import annotations

import logging
import struct
import subprocess
import zlib
from pathlib import Path

import pytest
from support.c_binding import (
    CClient,
    NvState,
    c_view,
    cbuf,
    compiled_core,
    library,
    out_frames,
    ref,
)

from canergy.cli import main
from canergy.cli import supervisor as supervisor_cli
from canergy.core import Client, LocalProtocolError, Supervisor
from canergy.core.actions import Send
from canergy.core.state import ClientState, Phase, Session, SupervisorState
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import ServiceConfig
from canergy.live.supervisor.state_file import StateFileError, load_state, save_state
from canergy.messages import (
    COUNTER_BOUND,
    COUNTER_END,
    SYNC_CONFIRMED,
    Ack,
    Admit,
    Committed,
    Debit,
    Intention,
    Join,
    Return,
    ReturnAck,
    Telemetry,
)
from firmware_model.nvstore import NvError, NvStore, encode_slot, pack_record

FIRMWARE = Path(__file__).resolve().parents[1] / "firmware"
J = 1_000_000
U32 = 2**32 - 1
CORES = {"python": Supervisor, "c": compiled_core}
BEYOND = [COUNTER_BOUND, 2**32 - 1, 2**63 - 1]
"""The bound itself, the C record's 32-bit end, the state loader's old limit."""


def _books(node: int, **counters: int) -> SupervisorState:
    return SupervisorState(10 * J, 10 * J, 0, (Session(node, **counters),))


def _refusal(value: int) -> str:
    return f"{value} is beyond the bound 2^30 - 1 the proof assumes"


# -- loading: the supervisor's state file ------------------------------------------------------


@pytest.mark.parametrize("field", ["tx", "returns_credited"])
def test_a_state_file_at_the_bound_loads_in_both_cores(field: str, tmp_path: Path) -> None:
    path = tmp_path / "sup.json"
    save_state(path, _books(3, **{field: COUNTER_BOUND - 1}), "hardened", fsync=False)
    state = load_state(path, "hardened", (3,))
    assert state is not None and getattr(state.sessions[0], field) == COUNTER_BOUND - 1
    for core in CORES.values():
        assert getattr(core([3], 0, state=state).session(3), field) == COUNTER_BOUND - 1


@pytest.mark.parametrize("value", BEYOND)
@pytest.mark.parametrize("field", ["tx", "returns_credited"])
def test_a_state_file_beyond_the_bound_is_refused_naming_the_field(
    field: str, value: int, tmp_path: Path
) -> None:
    path = tmp_path / "sup.json"
    save_state(path, _books(3, **{field: value}), "hardened", fsync=False)
    with pytest.raises(StateFileError) as refused:
        load_state(path, "hardened", (3,))
    assert str(refused.value) == f"{path}: sessions.3.{field}: {_refusal(value)}"
    for core in CORES.values():  # a state handed to a core directly: refused alike
        with pytest.raises(ValueError) as direct:
            core([3], 0, state=_books(3, **{field: value}))
        assert str(direct.value) == f"node 3: {field} {_refusal(value)}"


@pytest.mark.parametrize("core", CORES)
def test_the_supervisor_refuses_to_start_on_such_a_file(
    core: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    served: list[object] = []
    monkeypatch.setattr(supervisor_cli, "serve_supervisor", lambda *a, **kw: served.append(a))
    path = tmp_path / "sup.json"
    save_state(path, _books(3, tx=COUNTER_BOUND), "hardened", fsync=False)
    bus = ["-i", "virtual", "-c", f"end-{core}-{tmp_path.name}", "--nodes", "3"]
    code = main(["supervisor", *bus, "--state", str(path), "--core", core, "--no-fsync"])
    err = capsys.readouterr().err
    assert code == 2 and f"sessions.3.tx: {_refusal(COUNTER_BOUND)}" in err, err
    assert not served


# -- moving: both supervisor cores at the end of a node's numbering ----------------------------


def _sent(actions: list[object]) -> list[object]:
    return [a.message for a in actions if isinstance(a, Send)]


@pytest.mark.parametrize("core", CORES)
def test_the_last_transaction_below_the_end_runs_and_the_next_is_refused(core: str) -> None:
    sup = CORES[core]([3], 0, state=_books(3, tx=COUNTER_END - 2))
    assert _sent(sup.begin(3, 1000, 0)) == [Intention(3, (COUNTER_END - 1) & 0xFFFF, 1, 0)]
    sup.receive(Ack(3, (COUNTER_END - 1) & 0xFFFF), 1)
    sup.commit(3, 2)
    sup.receive(Committed(3, (COUNTER_END - 1) & 0xFFFF), 3)
    assert sup.session(3).phase is Phase.IDLE and sup.session(3).tx == COUNTER_END - 1
    before = sup.state
    with pytest.raises(LocalProtocolError, match=f"transaction {COUNTER_END - 1} is the last"):
        sup.begin(3, 1000, 4)
    assert sup.state == before  # nothing reserved, nothing sent


@pytest.mark.parametrize("tx", [COUNTER_END, COUNTER_BOUND - 1])
@pytest.mark.parametrize("core", CORES)
def test_a_record_past_the_end_but_below_the_bound_begins_nothing(core: str, tx: int) -> None:
    sup = CORES[core]([3], 0, state=_books(3, tx=tx))
    with pytest.raises(LocalProtocolError, match="its books must start again"):
        sup.begin(3, 1000, 0)


@pytest.mark.parametrize("core", CORES)
def test_no_return_is_credited_at_the_end(core: str) -> None:
    sup = CORES[core]([3], 0, state=_books(3, returns_credited=COUNTER_END - 2))
    last = (COUNTER_END - 1) & 0xFFFF
    assert _sent(sup.receive(Return(3, last, 5), 0)) == [ReturnAck(3, last)]
    assert sup.session(3).returns_credited == COUNTER_END - 1 and sup.usable == 10 * J + 5000
    before = sup.state
    assert sup.receive(Return(3, COUNTER_END & 0xFFFF, 5), 1) == []  # not credited, not acked
    assert sup.state == before
    assert _sent(sup.receive(Return(3, last, 5), 2)) == [ReturnAck(3, last)]  # re-acked


@pytest.mark.parametrize(
    ("tx", "seq"),
    [(COUNTER_END - 1, 5), (5, COUNTER_END - 1), (COUNTER_BOUND - 1, 0), (0, COUNTER_BOUND - 1)],
)
def test_an_admissions_lift_stays_below_the_end_alike_in_both_cores(tx: int, seq: int) -> None:
    """The lift puts both counters under the larger high part: below ``COUNTER_END`` from
    counters below it, below the bound from a record at it; the two cores agree."""
    after = []
    for core in CORES.values():
        sup = core([3], 0, state=_books(3, tx=tx, returns_credited=seq))
        sup.receive(Join(3, 0x1234), 0)
        after.append((sup.session(3).tx, sup.session(3).returns_credited))
    assert after[0] == after[1]
    limit = COUNTER_END if max(tx, seq) < COUNTER_END else COUNTER_BOUND
    assert max(after[0]) < limit and after[0][0] >= tx and after[0][1] >= seq


def test_a_client_takes_the_last_transaction_and_no_more_in_both_cores() -> None:
    """One step each, Python and C (every cell near the end: tests/test_c_hardened.py)."""
    start = ClientState(2, last_tx=COUNTER_END - 2)
    for tx, acked in ((COUNTER_END - 1, True), (COUNTER_END, False)):
        py = Client(2, state=start)
        c = CClient(2, state=start)
        sent = _sent(py.receive(Intention(2, tx & 0xFFFF, 4, 0), 0))
        out = c.message(Intention(2, tx & 0xFFFF, 4, 0), 0)
        assert sent == ([Ack(2, tx & 0xFFFF)] if acked else [])
        assert len(out_frames(out)) == len(sent) and c.view() == c_view(py.state)


@pytest.mark.parametrize("seq", [COUNTER_END - 2, COUNTER_END - 1, COUNTER_BOUND - 1])
def test_a_witnessed_client_debits_up_to_the_end_and_no_further_in_both_cores(seq: int) -> None:
    """No draw or return is numbered ``COUNTER_END`` or beyond (witnessed ``can_debit``)."""
    start = ClientState(2, usable=5 * J, return_seq=seq)
    room = seq + 1 < COUNTER_END
    for amount in (J, 2 * J):
        py, c = (
            Client(2, state=start, variant="witnessed"),
            CClient(2, state=start, rules="witnessed"),
        )
        assert py.can_spend() == py.can_give_back() == c.can_give_back() == room
        assert library().canergy_client_can_draw(c.c) == room
        for py_debit, c_debit in ((py.spend, c.do_draw), (py.give_back, c.do_give_back)):
            if room:
                py_debit(amount, 0)
                assert c_debit(amount, 0) == 0
                assert c.view() == c_view(py.state)
                break
            with pytest.raises(LocalProtocolError, match="last below"):
                py_debit(amount, 0)
            assert c_debit(amount, 0) != 0 and c.view() == c_view(start)


# -- loading: client NV records (emulator, C library, C node) ----------------------------------


def _nv_file(path: Path, *records: ClientState) -> Path:
    """An NV file whose slot 0 holds the first record, slot 1 the second (newer)."""
    slots = [encode_slot(i + 1, pack_record(r)) for i, r in enumerate(records)]
    path.write_bytes(b"".join(slots).ljust(80, b"\0"))
    return path


@pytest.mark.parametrize("field", ["last_tx", "return_seq"])
def test_an_nv_record_at_the_bound_loads(field: str, tmp_path: Path) -> None:
    path = _nv_file(tmp_path / "n.nv", ClientState(1, **{field: COUNTER_BOUND - 1}))
    loaded = NvStore(path, 1, fsync=False).load()
    assert loaded is not None and getattr(loaded, field) == COUNTER_BOUND - 1


@pytest.mark.parametrize("value", [COUNTER_BOUND, 2**32 - 1])  # the NV field is 32 bits
@pytest.mark.parametrize("field", ["last_tx", "return_seq"])
def test_an_nv_record_beyond_the_bound_is_refused_not_rolled_back(
    field: str, value: int, tmp_path: Path
) -> None:
    """The emulator refuses it naming the field (not the older slot: an older copy would give
    back what was spent); the C library takes it as no books, so the node JOINs."""
    good = ClientState(1, usable=5000, last_tx=7)
    path = _nv_file(tmp_path / "n.nv", good, ClientState(1, **{field: value}))
    with pytest.raises(NvError) as refused:
        NvStore(path, 1, fsync=False).load()
    assert str(refused.value) == f"--nv {path}: node 1: {field} {_refusal(value)}"
    image = path.read_bytes()
    state = NvState()
    library().canergy_nv_load(cbuf(image), len(image), ref(state))
    assert not state.books and state.fallbacks == 1


def _built(target: str) -> Path:
    build = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE), target], capture_output=True, text=True, timeout=600
    )
    assert build.returncode == 0, build.stdout + build.stderr
    return FIRMWARE / target


def _run(argv: list[str], tmp: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, timeout=10, cwd=tmp)


@pytest.mark.parametrize("value", [COUNTER_BOUND - 1, COUNTER_BOUND, 2**32 - 1])
@pytest.mark.parametrize("field", ["last_tx", "return_seq"])
def test_the_c_node_refuses_such_a_record_before_the_bus(
    field: str, value: int, tmp_path: Path
) -> None:
    node = _built("build/canergy-node")
    path = _nv_file(tmp_path / "n.nv", ClientState(1, **{field: value}))
    before = path.read_bytes()
    argv = [str(node), "--node", "1", "-i", "socketcan", "-c", "nosuchcan0", "--nv", "n.nv"]
    run = _run(argv, tmp_path)
    assert run.returncode == 2 and path.read_bytes() == before
    if value < COUNTER_BOUND:  # past the check: the bus, which does not exist here, stops it
        assert "beyond" not in run.stderr, run.stderr
    else:
        assert run.stderr == f"canergy-node: error: --nv n.nv: node 1: {field} {_refusal(value)}\n"


# -- loading: the C gateway's NV file (both roles in one slot) ---------------------------------

GW_NODES = 127  # CANERGY_SUPERVISOR_NODES of the gateway's build
SUP_SLOT = 40 + 56 * GW_NODES


def _supervisor_slot(node: int, tx: int, seq: int) -> bytes:
    """canergy_supervisor_image for one IDLE session (firmware/src/supervisor.c's layout)."""
    head = struct.pack("<IBBBBIQQQ", 0x534E5243, 5, 1, 0, 0, 1, 0, 0, 0)
    session = struct.pack("<BBBBIIIQQ6I", node, 0, 0, 0, tx, seq, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    body = head + session
    return (body + struct.pack("<I", zlib.crc32(body))).ljust(SUP_SLOT, b"\0")


def _gateway_slot(counter: int, up: ClientState, tx: int = 0, seq: int = 0) -> bytes:
    body = struct.pack("<II", 0x47524E43, counter) + pack_record(up) + _supervisor_slot(2, tx, seq)
    return body + struct.pack("<I", zlib.crc32(body))


BELOW = "downstream: a node's tx or returns_credited is beyond the bound 2^30 - 1 the proof assumes"


@pytest.mark.parametrize(
    ("newer", "words"),
    [
        ({"up": ClientState(1, last_tx=COUNTER_BOUND)}, f"upstream: last_tx {_refusal(2**30)}"),
        ({"up": ClientState(1, return_seq=2**32 - 1)}, f"upstream: return_seq {_refusal(U32)}"),
        ({"tx": COUNTER_BOUND}, BELOW),
        ({"seq": 2**32 - 1}, BELOW),
        ({"tx": COUNTER_BOUND - 1, "seq": COUNTER_BOUND - 1}, None),
    ],
)
def test_the_c_gateway_refuses_a_record_beyond_the_bound_in_either_role(
    newer: dict[str, object], words: str | None, tmp_path: Path
) -> None:
    gateway = _built("build/canergy-gateway")
    up = newer.pop("up", ClientState(1, last_tx=9))
    older = _gateway_slot(1, ClientState(1, last_tx=5))  # a valid older copy: never taken
    (tmp_path / "g.nv").write_bytes(older + _gateway_slot(2, up, **newer))  # type: ignore[arg-type]
    argv = [str(gateway), "--node", "1", "--nodes", "2", "-c", "nosuchcan0"]
    run = _run([*argv, "--upstream-channel", "nosuchcan1", "--nv", "g.nv"], tmp_path)
    assert run.returncode == 2
    if words is None:  # at the bound: past the check, the bus stops it
        assert "beyond" not in run.stderr, run.stderr
    else:
        assert run.stderr == f"canergy-gateway: error: --nv g.nv: {words}\n"


@pytest.mark.parametrize("core", CORES)
def test_the_live_supervisor_answers_a_grant_at_the_end_and_warns_once(
    core: str, caplog: pytest.LogCaptureFixture
) -> None:
    sup = CORES[core]([4], 0, state=_books(4, tx=COUNTER_END - 1))
    service = build_service(sup, ServiceConfig(), 0)
    service.on_message(Telemetry(4, 0), 1)
    replies: list[dict[str, object]] = []
    with caplog.at_level(logging.WARNING, logger="canergy"):
        for now in (2, 3):
            service.request_grant(4, J, replies.append)
            assert service.on_wakeup(now) == []
    assert [r["error"] for r in replies] == [
        f"node 4: transaction {COUNTER_END - 1} is the last below 1,073,676,288 (2^30 - 2^16, the "
        "bound the proof assumes less the admission's room): its books must start again (a new "
        "state file; with --auth keys of a new epoch)"
    ] * 2
    assert len([r for r in caplog.records if "is the last below" in r.getMessage()]) == 1
    assert service.status()["usable_uj"] == 10 * J  # nothing reserved


# -- moving: a witnessed start's void and a SYNC's lift at the bound -------------------------


@pytest.mark.parametrize("seq", [COUNTER_END - 1, COUNTER_BOUND - 2, COUNTER_BOUND - 1])
def test_a_witnessed_start_voids_below_the_bound_alike_in_both_cores(seq: int) -> None:
    """A RESUME's void (max(C, q) + 1) and a JOIN's (C + 1) stay below ``COUNTER_BOUND``: held
    at 2**30 - 1, where numbers only void, so the state file still loads (the voids above
    ``COUNTER_END`` were unbounded: a record at 2**30 - 1 confirmed a start to 2**30)."""
    for first in (Debit(3, 0x1234, Debit.START, seq & 0xFFFF, 0), Join(3, 0x1234)):
        after = []
        for core in CORES.values():
            sup = core([3], 0, state=_books(3, returns_credited=seq), variant="witnessed")
            sent = _sent(sup.receive(first, 0))
            after.append((sup.session(3).returns_credited, sent))
        assert after[0] == after[1]
        assert after[0][0] == min(seq + 1, COUNTER_BOUND - 1)
        assert after[0][1][-1].seq == after[0][0] & 0xFFFF


def test_a_witnessed_node_at_the_bound_answers_a_sync_below_it_in_both_cores() -> None:
    """A SYNC lifts ltx by B, held below the bound; a confirmation beyond it is ignored."""
    start = ClientState(2, usable=J, last_tx=COUNTER_BOUND - 2, return_seq=COUNTER_BOUND - 1)
    py = Client(2, state=start, variant="witnessed")
    c = CClient(2, state=start, rules="witnessed")
    sync = Admit(2, 0x0042, 0, (COUNTER_BOUND - 1) & 0xFFFF)
    sent = _sent(py.receive(sync, 0))
    out = c.message(sync, 0)
    assert py.state.last_tx == COUNTER_BOUND - 1 and len(sent) == len(out_frames(out)) == 2
    assert c.view() == c_view(py.state)
    beyond = Admit(2, 0x0042 ^ SYNC_CONFIRMED, 0, COUNTER_BOUND & 0xFFFF)
    before = py.state
    assert _sent(py.receive(beyond, 1)) == [] and py.state == before
    c.message(beyond, 1)
    assert c.view() == c_view(before)
