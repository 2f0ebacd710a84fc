"""The C witness and gateway policy (firmware/src/witness.c, gateway.c's top-up and give-back)
side by side with their Python twins: ``canergy.live.supervisor.witness.ReturnGate`` decision for
decision
(what a TELEMETRY finds, what a RETURN or RESUME becomes, what is released and when, which node
is blocked, the counts the status shows); ``TopUp`` capped by ``capped_grant``, and
``canergy.live.gateway.process.give_back_amount``, for every level, Us and setting.

The C gate holds at most ``SLOTS`` return numbers per node; the machine stays within them (an
honest node holds one), and ``test_a_return_beyond_the_slots_is_dropped_never_credited`` shows
what happens beyond."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule, run_state_machine_as_test
from support.c_binding import NEVER, CSession, Msg
from support.c_witness import (
    CONTRADICTED,
    FULL,
    HELD,
    OLD,
    RESTARTED,
    SAW,
    SINCE_START,
    SLOTS,
    WENT_BACK,
    CRelease,
    CWitness,
    policy_library,
)

from canergy.live.gateway.process import give_back_amount
from canergy.live.supervisor.policy import Limits, TopUp, capped_grant
from canergy.live.supervisor.witness import ReturnGate
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, SEQ_BITS, Debit, Return, Telemetry
from canergy.seqnum import unwrap

NODE = 4
HOLD_US = 500_000
BLOCK_US = 10_000_000
TELEMETRY, RETURN, DEBIT = 0x9, 0xC, 0xF  # enum canergy_msg_type
FINDINGS = {
    "the node saw": SAW,
    "its TELEMETRY contradicts": WENT_BACK,
    "the node reports": SINCE_START,
    "the node's witness count went back": RESTARTED,
}


def _msg(kind: int, **fields: int) -> Msg:
    return Msg(type=kind, node=NODE, **fields)


def _findings(lines: list[str]) -> int:
    bits = 0
    for line in lines:
        bits |= next(bit for prefix, bit in FINDINGS.items() if line.startswith(prefix))
    return bits


def _released(out: CRelease) -> list[Return | Debit]:
    """The C release, message by message (``canergy_witness_release_at``), as Python's list."""
    msgs: list[Return | Debit] = []
    m = Msg()
    while policy_library().canergy_witness_release_at(out, NODE, len(msgs), m):
        if m.type == RETURN:
            msgs.append(Return(m.node, m.seq, m.amount_mj))
        else:
            msgs.append(Debit(m.node, m.nonce, m.flags, m.seq, m.amount_mj))
    return msgs


class WitnessSideBySide(RuleBasedStateMachine):
    """One node's TELEMETRY, RETURNs and RESUMEs in any order and at any time; the session's
    returns_credited moves as the rules credit what is released."""

    def __init__(self) -> None:
        super().__init__()
        self.lib = policy_library()
        self.py = ReturnGate(HOLD_US, BLOCK_US)
        self.c = CWitness()
        self.lib.canergy_witness_init(self.c)
        self.now = 1_000
        self.credited = 0

    @rule(credited=st.sampled_from([0, 5, 65_530, 131_071, 2**30 - 70_000]))
    def books(self, credited: int) -> None:
        """The session's count anywhere (a fresh machine's, or after a start): the wire's
        16 bits wrap near some of them."""
        if not self.py.nodes and self.credited == 0:
            self.credited = credited

    @rule(dt=st.sampled_from([0, 1, 100_000, HOLD_US - 1, HOLD_US, BLOCK_US]))
    def later(self, dt: int) -> None:
        self.now += dt

    @rule(
        seen=st.sampled_from([0, 0, 1, 2, 128, 129, 255]),
        ahead=st.one_of(st.integers(-3, 3), st.integers(-70_000, 70_000)),
        joining=st.booleans(),
    )
    def telemetry(self, seen: int, ahead: int, joining: bool) -> None:
        w = self.py.nodes.get(NODE)
        count = ((w.witness if w is not None and w.witness is not None else 0) + seen) % 256
        seq = (self.credited + ahead) % 65536
        flags = Telemetry.JOINING if joining else 0
        evidence, notes = self.py.telemetry(
            Telemetry(NODE, 0, flags, seq, count), self.credited, self.now
        )
        m = _msg(TELEMETRY, flags=flags, seq=seq, witness=count)
        found = self.lib.canergy_witness_telemetry(self.c, m, self.credited, self.now)
        assert found == _findings(evidence + notes)

    @rule(ahead=st.integers(0, 3))
    def confirmed(self, ahead: int) -> None:
        """The node's own report: no frame seen in its name, its return number ``ahead``."""
        w = self.py.nodes.get(NODE)
        self.telemetry(0 if w is None or w.witness is not None else 1, ahead, False)

    @rule(ahead=st.integers(-1, 2), amount=st.sampled_from([0, 1, 7]))
    def returned(self, ahead: int, amount: int) -> None:
        msg = Return(NODE, (self.credited + ahead) % 65536, amount)
        old = self.py.old(msg, self.credited)
        evidence = None if old else self.py.hold(msg, self.credited, self.now)
        m = _msg(RETURN, seq=msg.seq, amount_mj=amount)
        verdict = self.lib.canergy_witness_hold(self.c, m, self.credited, self.now)
        assert verdict == (OLD if old else CONTRADICTED if evidence else HELD)

    @rule(
        nonce=st.sampled_from([1, 2]),
        ahead=st.sampled_from([1, 1, -1, 0, 2]),
        amount=st.sampled_from([3, 3, 0]),
        draw=st.sampled_from([False, False, True]),
        hold=st.sampled_from([True, True, False]),
    )
    def resumed(self, nonce: int, ahead: int, amount: int, draw: bool, hold: bool) -> None:
        flags = Debit.START | (Debit.DRAW if draw else 0)
        msg = Debit(NODE, nonce, flags, (self.credited + ahead) % 65536, amount)
        held = self.py.hold_resume(msg, self.credited, self.now, hold)
        m = _msg(DEBIT, nonce=nonce, flags=flags, seq=msg.seq, amount_mj=amount)
        assert held == self.lib.canergy_witness_hold_resume(
            self.c, m, self.credited, self.now, hold
        )

    @rule(dt=st.sampled_from([0, HOLD_US]))
    def release(self, dt: int) -> None:
        """What is released is credited (a RESUME's pending return too), in order."""
        self.now += dt
        expected = self.py.release(NODE, self.credited, self.now)
        out = CRelease()
        self.lib.canergy_witness_release(self.c, self.credited, self.now, HOLD_US, out)
        assert _released(out) == expected
        for msg in expected:
            self.credited += (msg.seq - self.credited) % 65536

    @rule()
    def readmitted(self) -> None:
        self.py.readmitted(NODE)
        self.lib.canergy_witness_readmitted(self.c)

    @invariant()
    def alike(self) -> None:
        w, c = self.py.nodes.get(NODE), self.c
        held = {
            h.seq: (h.amount_mj, h.confirmed_at if h.confirmed else None)
            for h in c.held[0 : c.held_count]
        }
        resume = (c.resume.seq, c.resume_held.confirmed_at if c.resume_held.confirmed else None)
        if w is None:
            assert (c.held_count, c.has_resume, c.has_witness, c.has_evidence) == (0, 0, 0, 0)
            return
        assert held == {n: (h.amount_mj, h.confirmed_at) for n, h in w.held.items()}
        assert c.held_count <= SLOTS
        py_resume = None if w.resume is None else (w.resume[0].seq, w.resume[1].confirmed_at)
        assert (resume if c.has_resume else None) == py_resume
        assert (c.return_seq if c.has_return_seq else None) == w.return_seq
        assert (c.witness if c.has_witness else None) == w.witness
        assert (c.evidence_at if c.has_evidence else None) == w.evidence_at
        assert (c.refuted, c.resynced) == (w.refuted, w.resynced)
        assert c.confirmed_at == w.confirmed_at
        blocked = self.lib.canergy_witness_blocked(c, self.now, BLOCK_US)
        assert blocked == self.py.blocked(NODE, self.now)
        nxt = self.lib.canergy_witness_next_release(c, HOLD_US)
        assert (None if nxt == NEVER else nxt) == self.py.next_release()


def test_the_c_witness_decides_as_the_python_return_gate() -> None:
    run_state_machine_as_test(
        WitnessSideBySide, settings=settings(max_examples=400, stateful_step_count=40)
    )


@pytest.mark.parametrize("credited", [0, 65_535, 2**30 - 70_000])
def test_a_resynchronisation_and_a_resume_alike_step_by_step(credited: int) -> None:
    """The machine's rarer paths, scripted: a RETURN numbered one past the next, confirmed and
    released with the missed number as 0 mJ; a RESUME owing the next return, confirmed and
    released; evidence dropping one held, and the block it starts."""
    m = WitnessSideBySide()
    m.books(credited)
    for step in (
        lambda: m.returned(2, 7),
        lambda: m.confirmed(2),
        lambda: m.release(HOLD_US),
        lambda: m.resumed(1, 1, 3, False, True),
        lambda: m.confirmed(1),
        lambda: m.release(HOLD_US),
        lambda: m.returned(1, 5),
        lambda: m.telemetry(1, 1, False),
        lambda: m.later(BLOCK_US - 1),
        lambda: m.release(0),
    ):
        step()
        m.alike()
    w = m.py.nodes[NODE]
    assert (w.resynced, w.refuted, m.credited) == (1, 1, credited + 3)


def test_a_return_beyond_the_slots_is_dropped_never_credited() -> None:
    lib = policy_library()
    c = CWitness()
    lib.canergy_witness_init(c)
    verdicts = []
    for seq in range(1, SLOTS + 2):
        m = _msg(RETURN, seq=seq, amount_mj=9)
        verdicts.append(lib.canergy_witness_hold(c, m, 0, 0))
    assert verdicts == [HELD] * SLOTS + [FULL]
    t = _msg(TELEMETRY, seq=SLOTS + 1)
    assert lib.canergy_witness_telemetry(c, t, 0, 10) == 0
    out = CRelease()
    lib.canergy_witness_release(c, 0, 10 + HOLD_US, HOLD_US, out)
    assert [r.seq for r in out.returns[0 : out.count]] == list(range(1, SLOTS + 1))


_NEAR = [0, 999, 1_000, 1_001, AMOUNT_MAX_MJ * QUANTUM_UJ, 2**32 - 1, 2**32]
_ENERGY = st.one_of(
    st.integers(0, 2**33),
    st.sampled_from(_NEAR),
    st.builds(lambda at, d: max(0, at + d), st.sampled_from(_NEAR), st.integers(-(10**8), 10**8)),
)


@settings(max_examples=500)
@given(target=_ENERGY, minimum=_ENERGY, level=_ENERGY, usable=st.integers(-(2**33), 2**33))
def test_the_top_up_is_the_python_policys(
    target: int, minimum: int, level: int, usable: int
) -> None:
    wanted = TopUp(target, minimum).wanted(level)
    expected = capped_grant(
        wanted, limits=Limits(), level=level, usable=usable, granted_total=0, rate_tokens=None
    )
    assert policy_library().canergy_gateway_top_up(target, minimum, level, usable) == expected


@settings(max_examples=500)
@given(usable=st.integers(-(2**33), 2**33), keep=_ENERGY)
def test_the_give_back_is_the_python_uplinks(usable: int, keep: int) -> None:
    expected = give_back_amount(usable, keep)
    assert policy_library().canergy_gateway_give_back_amount(usable, keep) == expected


@settings(max_examples=500)
@given(
    kind=st.sampled_from([RETURN, DEBIT, TELEMETRY]),
    flags=st.sampled_from([0, Debit.DRAW, Debit.START, Debit.SYNC, Debit.BOOKS, Debit.START | 4]),
    credited=st.sampled_from([0, 1, 65_535, 65_536, 2**30 - 2]),
    ahead=st.integers(-2, 3),
    amount=st.sampled_from([0, 1, 2, 3, 65_535]),
    books=st.tuples(st.integers(0, 10**8), st.integers(0, 65_535_000), st.integers(0, 10**8)),
)
def test_beyond_the_books_is_the_supervisors_check(
    kind: int,
    flags: int,
    credited: int,
    ahead: int,
    amount: int,
    books: tuple[int, int, int],
) -> None:
    """SupervisorService._impossible for a RETURN or DEBIT (the rule restated: it is a method
    of the service): fresh (numbered next) and more than the books let the node hold."""
    delivered, reserved, returned = books
    returned = min(returned, delivered + reserved)
    session = CSession(
        delivered_uj=delivered,
        reserved_uj=reserved,
        returned_uj=returned,
        returns_credited=credited,
    )
    seq = (credited + ahead) % 65536
    m = _msg(kind, flags=flags, seq=seq, amount_mj=amount)
    answers = kind == DEBIT and flags & (Debit.SYNC | Debit.BOOKS)
    fresh = unwrap(seq, credited, SEQ_BITS) == credited + 1
    holdable = delivered + reserved - returned
    expected = kind != TELEMETRY and not answers and fresh and amount * QUANTUM_UJ > holdable
    lib = policy_library()
    assert lib.canergy_witness_beyond_books(session, m) == expected
