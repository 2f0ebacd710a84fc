"""The witnessed rules' supervisor side: a supervisor started from an older copy of its state
file creates no energy (docs/protocol.md, "Records restored from older copies"): the window,
SYNC at every start, the books and counts on the wire, no grant before every node confirmed,
and the bounded checker on both rule sets. The table's cells are in tests/test_witnessed.py."""

from __future__ import annotations

from dataclasses import dataclass, replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from canergy.auth.frames import FrameAuth, Layout
from canergy.ccore.supervisor import CompiledSupervisor
from canergy.check import Bounds, check
from canergy.codec import Codec, DecodeError, DecodeErrorReason
from canergy.core import Client, LocalProtocolError, Send, Supervisor, Timing
from canergy.core import witnessed as W
from canergy.core.actions import Admitted
from canergy.core.errors import WindowClosed
from canergy.core.inputs import COMMAND_TIMEOUT, RESPONSE_TIMEOUT, Begin, GiveBack, PowerLoss, Spend
from canergy.core.state import ClientState, Phase, Session, SupervisorState
from canergy.core.steps import ClientStep, SessionStep
from canergy.core.table import cell
from canergy.core.variants import Variant
from canergy.frozen import evolve
from canergy.messages import (
    SYNC_CONFIRMED,
    Admit,
    Debit,
    Direction,
    Join,
    Message,
    Return,
    ReturnAck,
)

CODEC = Codec()
nodes = st.integers(1, 127)
u16 = st.integers(0, 0xFFFF)


# -- the wire ---------------------------------------------------------------------------------
@given(nodes, u16, st.integers(0, 0xFFFFFF), u16, u16)
def test_the_answer_to_a_sync_round_trips(node: int, nonce: int, rc: int, q: int, ltx: int) -> None:
    books, counts = Debit.books(node, nonce, rc), Debit.counts(node, nonce, q, ltx)
    for msg in (books, counts):
        arbitration_id, data = CODEC.encode(msg)
        assert len(data) == 8
        assert CODEC.decode(arbitration_id, data, direction=Direction.TO_SUPERVISOR) == msg
    assert books.is_books and books.credited_mj == rc and not books.is_resume
    assert counts.is_counts and counts.is_resume and counts.pending_mj == 0


def _frame(flags: int, seq: int = 1, amount: int = 1, nonce: int = 7) -> tuple[int, bytes]:
    """A DEBIT frame with a good CRC, whatever its fields say."""
    msg = Debit(3, nonce, flags, seq, amount)
    return CODEC.encode(msg)


ACCEPTED = {
    Debit.DRAW,
    Debit.START,
    Debit.START | Debit.DRAW,
    Debit.START | Debit.SYNC,
    Debit.START | Debit.SYNC | Debit.RC_UNKNOWN,
    0x08,
    0x18,
}


@pytest.mark.parametrize("flags", [f for f in range(256) if f not in ACCEPTED])
def test_any_other_flags_are_refused(flags: int) -> None:
    with pytest.raises(DecodeError) as e:
        CODEC.decode(*_frame(flags))
    assert e.value.reason is DecodeErrorReason.OUT_OF_RANGE


def test_books_beyond_24_bits_and_draws_without_amount_or_with_a_nonce_are_refused() -> None:
    for frame in (
        _frame(Debit.BOOKS, amount=0x100),
        _frame(Debit.DRAW, amount=0, nonce=0),
        _frame(Debit.DRAW, nonce=5),
        _frame(Debit.BOOKS | Debit.RC_UNKNOWN, seq=1, amount=0),  # no Rc, yet one carried
        _frame(Debit.BOOKS | Debit.RC_UNKNOWN, seq=0, amount=1),
    ):
        with pytest.raises(DecodeError):
            CODEC.decode(*frame)
    assert CODEC.decode(*_frame(Debit.BOOKS, amount=0xFF)) == Debit.books(3, 7, 0xFF0001)
    unknown = CODEC.decode(*_frame(Debit.BOOKS | Debit.RC_UNKNOWN, seq=0, amount=0))
    assert unknown == Debit.books(3, 7, None) and unknown.is_books and unknown.rc_unknown


def test_a_sync_is_an_admit_the_node_did_not_ask_for() -> None:
    """No new type: SYNC travels as ADMIT (DLC 7); a booked node answers it."""
    _, data = CODEC.encode(Admit(3, 0x51, 7, 4))
    assert len(data) == 7
    node = Client(3, variant="witnessed")
    sent = [a.message for a in node.receive(Admit(3, 0x51, 7, 4), 0) if isinstance(a, Send)]
    assert [type(m) for m in sent] == [Debit, Debit] and node.state.phase is Phase.SYNCING


# -- the supervisor core ----------------------------------------------------------------------
TIMING = Timing(response_timeout_us=10, command_timeout_us=10, return_retry_us=10)


def _exchange(actions: list[object], sup: Supervisor, nodes_: dict[int, Client], now: int) -> None:
    """Deliver every frame sent, each to its receiver, until nobody sends anything."""
    queue = list(actions)
    while queue:
        a = queue.pop(0)
        if isinstance(a, Send):
            msg: Message = a.message
            if msg.TYPE.direction is Direction.TO_CLIENT:
                queue += nodes_[msg.node].receive(msg, now)  # type: ignore[arg-type]
            else:
                queue += sup.receive(msg, now)  # type: ignore[arg-type]


@pytest.mark.parametrize("rules", ["hardened", "witnessed"])
def test_a_supervisor_started_from_its_copy_before_a_grant(rules: str) -> None:
    """Issue 40, item 5: 4 J granted to node 1 and committed, the state file put back to its
    copy from before the grant: the hardened supervisor grants the 4 J again to node 2; the
    witnessed one grants nothing until both nodes have answered, and then has nothing to
    grant."""
    sup = Supervisor([1, 2], 4_000_000, variant=rules, timing=TIMING)
    clients = {n: Client(n, variant=rules, timing=TIMING) for n in (1, 2)}
    copy = sup.state
    _exchange(sup.begin(1, 4_000_000, 0), sup, clients, 0)
    _exchange(sup.commit(1, 0), sup, clients, 0)
    assert clients[1].state.usable == 4_000_000
    sup.state = copy
    sup.power_loss(1, nonce=0x5A5A)
    if rules == "hardened":
        _exchange(sup.begin(2, 4_000_000, 1), sup, clients, 1)
        _exchange(sup.commit(2, 1), sup, clients, 1)
        assert clients[2].state.usable == 4_000_000  # 8 J held of 4 J: created
        return
    assert sup.unconfirmed() == (1, 2)
    with pytest.raises(LocalProtocolError, match=r"waiting for node\(s\) 1, 2"):
        sup.begin(2, 1000, 1)
    _exchange(sup.handle_timer(1), sup, clients, 1)  # SYNC to both, answered, confirmed
    assert sup.unconfirmed() == () and sup.usable == 0
    assert sup.session(1).delivered == 4_000_000
    with pytest.raises(LocalProtocolError, match="exceeds usable"):
        sup.begin(2, 1000, 2)
    assert all(c.state.phase is Phase.IDLE for c in clients.values())


def test_a_node_that_is_off_holds_every_grant_unless_the_operator_starts_without_it() -> None:
    for without, waiting in (((), (1, 2)), ((2,), (1,))):
        sup = Supervisor([1, 2], 4000, variant="witnessed", timing=TIMING, start_without=without)
        node = Client(1, variant="witnessed", timing=TIMING)
        sup.power_loss(0, nonce=9)
        assert sup.unconfirmed() == waiting
        _exchange(sup.handle_timer(0), sup, {1: node, 2: Client(2, variant="witnessed")}, 0)
    sup = Supervisor([1, 2], 4000, variant="witnessed", timing=TIMING, start_without=(2,))
    sup.power_loss(0, nonce=9)
    only_1 = {1: Client(1, variant="witnessed", timing=TIMING)}
    for a in sup.handle_timer(0):
        if isinstance(a, Send) and a.message.node == 1:
            _exchange([a], sup, only_1, 0)
    assert sup.unconfirmed() == ()
    sup.begin(1, 1000, 1)  # node 2 (off) is not waited for; its own session still waits
    with pytest.raises(LocalProtocolError):
        sup.begin(2, 1000, 1)
    with pytest.raises(ValueError, match="start_without"):
        Supervisor([1], 1, variant="witnessed", start_without=(5,))


def test_hardened_books_never_wait() -> None:
    sup = Supervisor([1, 2], 4000, variant="hardened", timing=TIMING)
    sup.power_loss(0)
    assert sup.unconfirmed() == ()


# -- what the rules are for: the bounded checker ----------------------------------------------
SUP_COPY = Bounds(
    clients=2,
    supervisor_old_copies=1,
    transactions=1,
    losses=0,
    duplicates=0,
    power_losses=0,
    timeouts=3,
)
"""One older copy of the supervisor's state file, two nodes, one transaction."""


def test_an_older_copy_of_the_supervisors_state_file_creates_no_energy() -> None:
    hardened = check("hardened", SUP_COPY, stop_at_first=True, engine="compact")
    assert hardened.counterexample is not None
    last, world = hardened.counterexample[-1]
    assert last.kind.value == "supervisor_old_copy" and world.ledger().dissipated < 0
    witnessed = check("witnessed", SUP_COPY, engine="compact")
    assert witnessed.complete and witnessed.violations == 0
    assert witnessed.states > check("witnessed", replace(SUP_COPY, supervisor_old_copies=0)).states


def _books_ignored(t: Timing, s: Session, msg: Debit, now: int) -> SessionStep:
    """Takes the books without moving Gs up to Rc: Us keeps what the node received since."""
    if msg.nonce != s.sync_nonce or not msg.is_books:
        return SessionStep(s)
    return SessionStep(evolve(s, phase=Phase.SYNC_BOOKS))


def _answer_unsettled(t: Timing, c: ClientState, msg: Admit, now: int) -> ClientStep:
    """Answers a SYNC without settling the window ahead: a discarded history's intention can
    still be taken."""
    c = evolve(W.answer_sync(t, c, msg, now).client, last_tx=c.last_tx)
    return ClientStep(c, W.answer_of(c))


def _restart_unsynced(t: Timing, s: Session, event: object, now: int) -> SessionStep:
    """The hardened restart: no SYNC, grants at once."""
    return W.h.restart_session(t, s, event, now)  # type: ignore[arg-type]


def _broken(sup: object = None, client: object = None) -> Variant:
    s = W.SUPERVISOR.with_cells(sup) if sup else W.SUPERVISOR  # type: ignore[arg-type]
    c = W.CLIENT.with_cells(client) if client else W.CLIENT  # type: ignore[arg-type]
    return Variant("broken-witnessed", s, c, lifts_tx=True)


SY, ID, HO = Phase.SYNCING, Phase.IDLE, Phase.AWAIT_COMMAND


@pytest.mark.parametrize(
    "variant",
    [
        _broken(sup=cell(SY, Debit, _books_ignored, to=(Phase.SYNC_BOOKS, None))),
        _broken(client=cell((ID, HO), Admit, _answer_unsettled, to=SY)),
    ],
    ids=["books-not-taken", "answer-without-settling"],
)
def test_each_supervisor_witnessing_rule_is_needed(variant: Variant) -> None:
    result = check(variant, SUP_COPY, stop_at_first=True, engine="compact")
    assert result.counterexample is not None
    assert any(step.kind.value == "supervisor_old_copy" for step, _ in result.counterexample)


def _sent(step: SessionStep | ClientStep) -> list[Message]:
    return [a.message for a in step.actions if isinstance(a, Send)]


def test_a_start_that_answered_a_copy_of_the_same_sync_is_confirmed_at_its_ltx() -> None:
    """A SYNC re-sent by its timer, one copy answered and its counts taken; the node loses
    power while it waits and the other copy reaches its RESUME: a second start of the node with
    the supervisor's nonce, its counts ``B`` further, and otherwise a repeat of the first
    (same nonce and q, C unchanged). The supervisor moves tx up to their ltx and answers with
    the same C: the node keeps its books at tx. Before, the same answer came again (k ``B``
    below that ltx): the node stayed ahead of tx, the window's 64 transactions were written off
    as old; the witnessed proof's counterexample to 'supervisor receives DEBIT: P(ADMIT) sent'.
    W stays (counts outside a start are no evidence: another start of an earlier life may have
    answered the same SYNC), so the next begin waits for a re-sync of the node."""
    t = Timing()
    s = Session(node=1, tx=10, witness=10, returns_credited=3)
    c = ClientState(node=1, last_tx=10, return_seq=3, usable=5000, credited=5000)
    s = W.SUPERVISOR.step(t, s, PowerLoss(0x1234), 0).session
    step = W.SUPERVISOR.step(t, s, RESPONSE_TIMEOUT, 0)
    s, (first,) = step.session, _sent(step)
    step = W.SUPERVISOR.step(t, s, RESPONSE_TIMEOUT, t.response_timeout_us)
    s, (second,) = step.session, _sent(step)
    assert first == second
    answer = W.CLIENT.step(t, c, first, 0)
    c, (books, counts) = answer.client, _sent(answer)
    s = W.SUPERVISOR.step(t, s, books, 0).session
    step = W.SUPERVISOR.step(t, s, counts, 0)
    s, (confirmation,) = step.session, _sent(step)
    assert s.phase is Phase.IDLE and s.tx == s.witness == 10 + t.window
    c = W.CLIENT.step(t, c, PowerLoss(0x5678), 0).client
    answer = W.CLIENT.step(t, c, second, 0)
    c, (_, counts) = answer.client, _sent(answer)
    assert c.phase is Phase.SYNCING and c.nonce == 0x1234 and c.last_tx == 10 + 2 * t.window
    step = W.SUPERVISOR.step(t, s, counts, 0)
    s, (again,) = step.session, _sent(step)
    assert isinstance(again, Admit) and isinstance(confirmation, Admit)
    assert s.tx == c.last_tx and step.credit == 0
    assert s.witness == 10 + t.window  # counts outside a start move no W (``repeat_counts``)
    assert (again.nonce, again.seq) == (confirmation.nonce, confirmation.seq)  # C unchanged
    assert again.tx == c.last_tx != confirmation.tx
    c = W.CLIENT.step(t, c, again, 0).client
    assert c.phase is Phase.IDLE and c.usable == 5000 and c.last_tx == s.tx
    with pytest.raises(WindowClosed):  # a re-sync of the node opens it (the live service's)
        W.SUPERVISOR.step(t, s, Begin(1000), t.response_timeout_us)


@dataclass(frozen=True)
class _OneCopyAnswered:
    """A SYNC sent twice (its timer); the node, from ``image``, answered the first copy and was
    confirmed (``c``, ``s``); ``second`` is the other copy, still in flight."""

    t: Timing
    s: Session
    image: ClientState
    c: ClientState
    second: Message
    counts: Message
    confirmation: Message


def _one_copy_answered() -> _OneCopyAnswered:
    t = Timing()
    s = Session(node=1, tx=10, witness=10, returns_credited=3, delivered=5000)
    image = ClientState(node=1, last_tx=10, return_seq=3, usable=5000, credited=5000)
    s = W.SUPERVISOR.step(t, s, PowerLoss(0x1234), 0).session
    step = W.SUPERVISOR.step(t, s, RESPONSE_TIMEOUT, 0)
    s, (first,) = step.session, _sent(step)
    step = W.SUPERVISOR.step(t, s, RESPONSE_TIMEOUT, t.response_timeout_us)
    s, (second,) = step.session, _sent(step)
    answer = W.CLIENT.step(t, image, first, 0)
    c, (books, counts) = answer.client, _sent(answer)
    s = W.SUPERVISOR.step(t, s, books, 0).session
    step = W.SUPERVISOR.step(t, s, counts, 0)
    s, (confirmation,) = step.session, _sent(step)
    c = W.CLIENT.step(t, c, confirmation, 0).client
    return _OneCopyAnswered(t, s, image, c, second, counts, confirmation)


def test_counts_repeated_by_an_older_image_while_a_grant_is_open_write_it_off() -> None:
    """The node answers one copy of a SYNC, is confirmed and takes the grant begun next; put
    back to its record from before the SYNC, it answers the other copy: the same counts (same
    nonce, q and ltx), a repeat. Answered as before (k = tx - 1 while tx is open), the image
    took a copy of INTENTION(tx) as fresh and received again what its earlier record had
    received once: over the node's records, twice what the supervisor delivered (the witnessed
    proof's counterexample to 'supervisor receives DEBIT: P(ADMIT) sent'). Now what is open is
    written off first and the answer's k is tx: the copy is old to the image."""
    run = _one_copy_answered()
    t, s, image, c = run.t, run.s, run.image, run.c
    second, counts, confirmation = run.second, run.counts, run.confirmation
    step = W.SUPERVISOR.step(t, evolve(s, witness=s.tx), Begin(1000), 0)  # a re-sync's W
    s, (intention,) = step.session, _sent(step)
    c = W.CLIENT.step(t, c, intention, 0).client
    assert c.deadline is not None
    earlier = W.CLIENT.step(t, c, COMMAND_TIMEOUT, c.deadline).client  # its timeout-commit
    assert earlier.usable == 6000 and s.phase is Phase.WAIT_ACK
    c = W.CLIENT.step(t, image, PowerLoss(0x5678), 0).client  # the image, started
    answer = W.CLIENT.step(t, c, second, 0)
    c, (_, again_counts) = answer.client, _sent(answer)
    assert again_counts == counts  # a repeat: nothing tells it from the first start's retry
    step = W.SUPERVISOR.step(t, s, again_counts, 0)
    s, (again,) = step.session, _sent(step)
    assert isinstance(again, Admit) and isinstance(intention, Message)
    assert s.phase is Phase.IDLE and s.delivered == 6000 and step.credit == 0  # written off
    assert (again.nonce, again.seq) == (confirmation.nonce, confirmation.seq)
    assert again.tx == s.tx == intention.tx
    c = W.CLIENT.step(t, c, again, 0).client
    late = W.CLIENT.step(t, c, intention, 0)
    assert _sent(late) == [] and late.client == c  # old to the image: not taken again


def test_a_return_of_the_record_an_image_repeats_the_counts_of_is_not_credited() -> None:
    """The node answers one copy of a SYNC, is confirmed (C = q + 1) and gives 1 mJ back as
    RETURN(q + 2), still in flight when it loses power; put back to its record from before the
    SYNC it answers the other copy: a repeat, the same answer, which confirms the image (Q one
    past its q) with the 1 mJ it still holds. Then the RETURN arrives: credited, as before, the
    supervisor held back what the image still spends (1 mJ created). The repeat voids C + 1:
    acknowledged, not credited, and the same counts once more are no repeat (found behind)."""
    run = _one_copy_answered()
    t, s, image, c = run.t, run.s, run.image, run.c
    second, counts, confirmation = run.second, run.counts, run.confirmation
    gave = W.CLIENT.step(t, c, GiveBack(1000), 0)
    (returned,) = _sent(gave)
    assert isinstance(returned, Return) and gave.client.usable == 4000
    answer = W.CLIENT.step(t, W.CLIENT.step(t, image, PowerLoss(0x5678), 0).client, second, 0)
    c, (_, again_counts) = answer.client, _sent(answer)
    assert again_counts == counts
    step = W.SUPERVISOR.step(t, s, again_counts, 0)
    s, (again,) = step.session, _sent(step)
    assert again == confirmation and s.returns_credited == returned.seq
    c = W.CLIENT.step(t, c, again, 0).client
    assert c.phase is Phase.IDLE and c.usable == 5000 and c.return_seq == returned.seq - 1
    step = W.SUPERVISOR.step(t, s, returned, 0)
    assert step.credit == 0 and step.session.returned == 0
    assert _sent(step) == [ReturnAck(1, returned.seq)]
    # the image's own debit numbered C + 1 is acknowledged too: a draw reaches its actuator
    drawing = W.CLIENT.step(t, c, Spend(1000), 0)
    (draw,) = _sent(drawing)
    assert isinstance(draw, Debit) and draw.seq == returned.seq
    held = W.SUPERVISOR.step(t, step.session, draw, 0)
    assert held.credit == 0 and held.session == step.session
    (ack,) = _sent(held)
    released = W.CLIENT.step(t, drawing.client, ack, 0).client
    assert released.spent == c.spent + 1000 and released.usable == 4000
    once_more = W.SUPERVISOR.step(t, step.session, again_counts, 0)
    assert any(isinstance(a, Admitted) for a in once_more.actions)  # found behind
    (fresh,) = _sent(once_more)
    assert isinstance(fresh, Admit) and fresh.seq != again.seq


def test_counts_repeated_with_an_ltx_above_tx_write_off_what_is_open() -> None:
    """The repeat with a higher ltx while a transaction is open: written off (Gs += Ts, the
    node settled it), tx up to the ltx (W not: counts outside a start are no evidence), the
    answer's C and the remembered answer unchanged, C + 1 voided after it."""
    t = Timing()
    s = Session(
        node=1, phase=Phase.WAIT_ACK, tx=75, reserved=2000, delivered=5000, witness=74,
        returns_credited=4, resume_nonce=0x11234, resume_from=3, resume_to=4,
    )  # fmt: skip
    counts = Debit.counts(1, 0x1234, 3, 138)
    step = W.SUPERVISOR.step(t, s, counts, 0)
    after = step.session
    assert after.phase is Phase.IDLE and after.delivered == 7000 and after.reserved == 0
    assert after.tx == 138 and after.witness == 74 and step.credit == 0
    assert (after.returns_credited, after.resume_to, after.resume_from) == (5, 4, 3)
    assert _sent(step) == [Admit(1, 0x1234 ^ SYNC_CONFIRMED, 138, 4)]
    lower = W.SUPERVISOR.step(
        t, replace(s, phase=Phase.IDLE, reserved=0), Debit.counts(1, 0x1234, 3, 70), 0
    )
    assert lower.session.tx == 75 and _sent(lower) == [Admit(1, 0x1234 ^ SYNC_CONFIRMED, 75, 4)]


def test_a_replayed_counts_frame_of_an_earlier_sync_moves_no_tx() -> None:
    """A node confirmed at tx 100,000; a counts frame it sent at an earlier SYNC (ltx 60,000),
    replayed with its MAC: verified (the key does not stop it), then ignored by the rules, which
    take counts outside a start only under the nonce of the last start answered, or with an ltx
    from tx to tx + B."""
    key = bytes(range(16))
    node_side = FrameAuth(CODEC, Layout.FD, lambda n: key, Direction.TO_CLIENT, lambda m: None)
    sup_side = FrameAuth(CODEC, Layout.FD, lambda n: key, Direction.TO_SUPERVISOR, lambda m: 0)
    old = Debit.counts(1, 0x0303, 10, 60_000)
    (frame,) = node_side.frames(old)
    verdict = sup_side.accept(frame)
    assert verdict.message == old and verdict.failure is None  # the key does not stop it
    s = Session(
        node=1, tx=100_000, witness=100_000, returns_credited=50, delivered=9000,
        resume_nonce=0x10707, resume_from=49, resume_to=50,
    )  # fmt: skip
    step = W.SUPERVISOR.step(Timing(), s, old, 0)
    assert step.session is s and step.actions == ()  # ignored: not the last start's nonce
    # the last start's counts (its answer lost) and a RESUME's resync are still taken
    again = W.SUPERVISOR.step(Timing(), s, Debit.counts(1, 0x0707, 49, 100_000 & 0xFFFF), 0)
    assert _sent(again) == [Admit(1, 0x0707 ^ SYNC_CONFIRMED, 100_000 & 0xFFFF, 50)]
    resumed = replace(s, resume_nonce=0x0707)  # RESUME(0x0707, 49) answered: C 50
    resync = W.SUPERVISOR.step(Timing(), resumed, Debit.counts(1, 0x0707, 50, 100_200 & 0xFFFF), 0)
    assert resync.session.tx == 100_200  # beyond B: by its nonce (W stays: no evidence)
    assert resync.session.witness == 100_000
    assert _sent(resync) == [Admit(1, 0x0707 ^ SYNC_CONFIRMED, 100_200 & 0xFFFF, 51)]
    walked = s  # three earlier SYNCs' counts, ltx spread over 2^16: tx stays
    for ltx in (0x0000, 0x5555, 0xAAAA):
        walked = W.SUPERVISOR.step(Timing(), walked, Debit.counts(1, 0x0303, 10, ltx), 0).session
    assert walked is s


ANSWERED = Session(
    node=1, tx=10, witness=10, returns_credited=50, resume_nonce=0x10707, resume_from=49,
    resume_to=50,
)  # fmt: skip
"""Idle after a start answered: the counts (0x0707, q 49) got ADMIT(0x8707, 10, 50)."""


@pytest.mark.parametrize("core", [Supervisor, CompiledSupervisor], ids=["python", "c"])
@pytest.mark.parametrize("how", ["re-sync", "start"])
def test_a_sync_never_takes_the_nonce_of_the_last_start_answered(
    core: type[Supervisor], how: str
) -> None:
    """A re-sync or a start handed the nonce of the last start answered (0x0707, or 0x8707
    with SYNC_CONFIRMED set) sends its SYNC under another (0x0706): counts under it with the
    same q would read as a repeat of that answer (the same ADMIT, C not voided, nothing
    taken). The node's counts under the SYNC's nonce are then taken afresh: found behind (q 49
    below C 50), C lifted, the answer remembered under the new nonce."""

    def answered() -> Supervisor:
        state = SupervisorState(0, 0, sessions=(ANSWERED,))
        return core([1], 0, variant="witnessed", timing=TIMING, state=state)

    sup = answered()
    if how == "re-sync":
        sent = [a.message for a in sup.resync(1, 0, nonce=0x8707) if isinstance(a, Send)]
        assert sent == [Admit(1, 0x0706, 10, 50)]
    else:
        sup.power_loss(0, nonce=0x0707)
    assert sup.session(1).sync_nonce == 0x0706
    sup.receive(Debit.books(1, 0x0706, 0), 1)
    answer = [
        a.message for a in sup.receive(Debit.counts(1, 0x0706, 49, 10), 1) if isinstance(a, Send)
    ]
    done = sup.session(1)
    assert done.phase is Phase.IDLE and done.resume_nonce == 0x10706
    assert done.returns_credited > 50 and len(answer) == 1
    assert answer[0].nonce == 0x0706 ^ SYNC_CONFIRMED  # type: ignore[union-attr]
    other = answered()
    other.resync(1, 0, nonce=0x0708)
    assert other.session(1).sync_nonce == 0x0708  # any other nonce as drawn


# -- an admission into C's higher 2^16 block --------------------------------------------------
LIFTED = Session(1, tx=10, witness=10, returns_credited=70_000)
"""C ran 65,536 numbers past tx's block (witnessed draws): tx 10, W 10, C 70,000."""


@pytest.mark.parametrize(
    "frame",
    [Join(1, 0x33), Debit(1, 0x34, Debit.START, 69_999 & 0xFFFF, 0)],
    ids=["join", "resume found behind"],
)
def test_an_admission_lifting_tx_leaves_w_and_a_resync_opens_the_window(
    frame: Join | Debit,
) -> None:
    """A JOIN, or a RESUME found behind, lifts tx into C's block (10 + 2^16); W stays at 10 (the
    admission is no evidence: its ADMIT may be lost, the frame a late one of an earlier start),
    so the next begin is refused as beyond the window (``WindowClosed``). A re-sync of the node
    takes its counts under the re-sync's nonce: tx and W move to the ltx the node settled, and
    the next transaction begins."""
    admitted = W.SUPERVISOR.step(TIMING, LIFTED, frame, 0).session
    assert (admitted.tx, admitted.witness) == (10 + (1 << 16), 10)
    with pytest.raises(WindowClosed, match="beyond the window"):
        W.SUPERVISOR.step(TIMING, admitted, Begin(1_000_000), 0)
    syncing = W.resync_session(TIMING, admitted, 0x8707, 5)  # SYNC_CONFIRMED cleared
    assert syncing.session.phase is Phase.SYNCING and syncing.session.resync
    assert syncing.actions == (Send(Admit(1, 0x0707, 10, 70_001 & 0xFFFF)),)
    ltx = admitted.tx + TIMING.window  # the node settled B past the ADMIT's k
    books = W.SUPERVISOR.step(TIMING, syncing.session, Debit.books(1, 0x0707, None), 5).session
    q = 70_001 & 0xFFFF
    done = W.SUPERVISOR.step(TIMING, books, Debit.counts(1, 0x0707, q, ltx & 0xFFFF), 5)
    assert (done.session.phase, done.session.tx, done.session.witness) == (Phase.IDLE, ltx, ltx)
    assert not done.session.resync
    assert _sent(done) == [Admit(1, 0x0707 ^ SYNC_CONFIRMED, ltx & 0xFFFF, 70_002 & 0xFFFF)]
    begun = W.SUPERVISOR.step(TIMING, done.session, Begin(1_000_000), 0).session
    assert begun.tx == ltx + 1


@pytest.mark.parametrize("core", [Supervisor, CompiledSupervisor], ids=["python", "c"])
def test_a_node_that_lost_its_books_gets_its_next_grant_after_a_lifting_join_and_a_resync(
    core: type[Supervisor],
) -> None:
    """End to end, both cores: the node loses its books (JOIN), is admitted at tx = 10 + 2^16
    with W left at 10; the next begin is refused as beyond the window; one re-sync (SYNC, the
    node's books and counts, the confirmation) and the node takes and commits the next grant.
    Another node meanwhile is not held up by the re-sync (``unconfirmed`` leaves it out)."""
    state = SupervisorState(5_000_000, 5_000_000, sessions=(LIFTED, Session(2)))
    sup = core([1, 2], 5_000_000, variant="witnessed", timing=TIMING, state=state)
    node = Client(1, variant="witnessed", timing=TIMING)
    other = Client(2, variant="witnessed", timing=TIMING, state=ClientState(2))
    nodes_ = {1: node, 2: other}
    _exchange(node.books_lost(0x33, 0), sup, nodes_, 0)
    assert node.state.phase is Phase.IDLE and sup.state.sessions[0].tx == 10 + (1 << 16)
    with pytest.raises(WindowClosed):
        sup.begin(1, 1_000_000, 1)
    sync = sup.resync(1, 1, nonce=0x0707)
    assert sup.unconfirmed() == () and sup.session(1).phase is Phase.SYNCING
    _exchange(sup.begin(2, 1_000_000, 1), sup, nodes_, 1)  # node 2 does not wait for node 1
    _exchange(sup.commit(2, 1), sup, nodes_, 1)
    _exchange(sync, sup, nodes_, 1)
    assert sup.session(1).phase is Phase.IDLE and node.state.phase is Phase.IDLE
    assert sup.session(1).witness == sup.session(1).tx == 10 + (1 << 16) + TIMING.window
    assert node.state.last_tx == 10 + TIMING.window  # the node counts from the ADMIT's 16 bits
    _exchange(sup.begin(1, 1_000_000, 2), sup, nodes_, 2)
    _exchange(sup.commit(1, 2), sup, nodes_, 2)
    assert sup.state.sessions[0].phase is Phase.IDLE and node.state.usable == 1_000_000
    assert sup.state.sessions[0].delivered == 1_000_000 and sup.state.usable == 3_000_000
