"""The C supervisor (firmware/src/supervisor.c) side by side with ``canergy.core.Supervisor``:
hypothesis drives both with the same grants, decisions, client frames (for managed nodes and
others, counters near the sessions' and anywhere, bytes that do not decode), timers, resets and
injections. After every step both hold the same Us and sessions, sent the same frames byte for
byte, asked to persist alike, and refused the same requests. The C supervisor's record is
written to its two NV slots whenever it asks (and after an injection), and a reset restarts it
from those bytes alone: so every change it must not lose was asked to be persisted."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import pytest
from hypothesis import Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    invariant,
    rule,
    run_state_machine_as_test,
)
from support.c_binding import (
    ERR_AMOUNT,
    ERR_ARGUMENT,
    ERR_PHASE,
    ERR_UNCONFIRMED,
    ERR_WINDOW,
    OK,
    RX_OTHER_NODE,
    SUPERVISOR_SLOT,
    CSupervisor,
    SupervisorConfig,
    SupervisorOut,
    cbuf,
    library,
    ref,
    rx,
)
from support.c_session import fields_of, timing_of
from support.strategies import client_answer

from canergy.codec import Codec
from canergy.core.actions import Persist, Send
from canergy.core.errors import LocalProtocolError
from canergy.core.state import SYNC_PHASES, Session
from canergy.core.supervisor import Supervisor
from canergy.core.timing import Timing
from canergy.messages import QUANTUM_UJ, Debit

NODES = (3, 5, 9)
T = Timing(response_timeout_us=1_000, retries=2)
CODEC = Codec()
amounts = st.one_of(
    st.integers(1, 3_000).map(lambda mj: mj * QUANTUM_UJ), st.sampled_from([0, 500, 65_536_000])
)


class SideBySide(RuleBasedStateMachine):
    VARIANT = ""
    variant = "hardened"

    def __init__(self) -> None:
        super().__init__()
        self.lib = library(self.VARIANT)
        self.py = Supervisor(NODES, 10_000_000, timing=T, variant=self.variant)
        self.c = CSupervisor(lib=self.lib)
        self.nv = cbuf(2 * SUPERVISOR_SLOT, lib=self.lib)
        self.nv_counter, self.nv_slot = self.lib.new("uint32_t *"), self.lib.new("uint8_t *")
        assert self._load() == 0  # blank NV: a new supervisor
        self.now = 0
        self.out = SupervisorOut(lib=self.lib)

    def _load(self) -> int:
        cfg = SupervisorConfig(
            id_base=CODEC.id_base, timing=timing_of(T, self.variant, self.lib), lib=self.lib
        )
        nodes = cbuf(bytes(NODES), lib=self.lib)
        return int(
            self.lib.canergy_supervisor_load(
                ref(self.c), ref(cfg), nodes, len(NODES), 10_000_000,
                self.nv, len(self.nv), ref(self.nv_counter), ref(self.nv_slot),
            )
        )  # fmt: skip

    def _persist(self) -> None:
        """Write the record to the other slot, as a port does before sending."""
        self.nv_slot[0] ^= 1
        self.nv_counter[0] += 1
        image = cbuf(SUPERVISOR_SLOT, lib=self.lib)
        self.lib.canergy_supervisor_image(ref(self.c), self.nv_counter[0], image)
        start = self.nv_slot[0] * SUPERVISOR_SLOT
        self.nv[start : start + SUPERVISOR_SLOT] = image

    def _same_actions(self, actions: list[Any]) -> None:
        if self.out.persist:
            self._persist()
        sent = [CODEC.encode(a.message) for a in actions if isinstance(a, Send)]
        frames = [
            (f.id, bytes(f.data[0 : f.dlc])) for f in self.out.frames[0 : self.out.frame_count]
        ]
        assert frames == [(i, bytes(d)) for i, d in sent]
        assert bool(self.out.persist) == any(isinstance(a, Persist) for a in actions)

    def _request(self, py: Any, c: Any) -> None:
        try:
            actions = py()
        except LocalProtocolError:
            assert c() in (ERR_AMOUNT, ERR_PHASE, ERR_ARGUMENT, ERR_WINDOW, ERR_UNCONFIRMED)
            return
        assert c() == OK
        self._same_actions(actions)

    @rule(node=st.sampled_from([*NODES, 4]), amount=amounts)
    def begin(self, node: int, amount: int) -> None:
        self._request(
            lambda: self.py.begin(node, amount, self.now),
            lambda: self.lib.canergy_supervisor_begin(
                ref(self.c), node, amount, self.now, ref(self.out)
            ),
        )

    @rule(node=st.sampled_from([*NODES, 4]), commit=st.booleans())
    def decide(self, node: int, commit: bool) -> None:
        self._request(
            lambda: (self.py.commit if commit else self.py.abort)(node, self.now),
            lambda: self.lib.canergy_supervisor_decide(
                ref(self.c), node, commit, self.now, ref(self.out)
            ),
        )

    @rule(data=st.data())
    def receive(self, data: st.DataObject) -> None:
        node = data.draw(st.sampled_from([*NODES, 4]))
        s = self.py.session(node) if node in NODES else None
        tx, credited = (0, 0) if s is None else (s.tx, s.returns_credited)
        msg = client_answer(data, node, tx, credited)
        arbitration_id, payload = CODEC.encode(msg)
        if data.draw(st.booleans(), label="damage a byte"):
            payload = bytearray(payload)
            payload[0] ^= 0x5A
        frame, _buf = rx(
            arbitration_id, bytes(payload), lib=self.lib
        )  # the buffer outlives the call
        status = self.lib.canergy_supervisor_on_frame(
            ref(self.c), ref(frame), self.now, ref(self.out)
        )
        try:
            decoded = CODEC.decode(arbitration_id, bytes(payload))
        except ValueError:
            assert status not in (OK, RX_OTHER_NODE) and self.out.frame_count == 0
            return
        if node not in NODES:
            assert status == RX_OTHER_NODE and self.out.frame_count == 0
            return
        assert status == OK
        self._same_actions(self.py.receive(decoded, self.now))

    @rule(dt=st.integers(0, 3_000))
    def timer(self, dt: int) -> None:
        self.now += dt
        actions = self.py.handle_timer(self.now)
        self.lib.canergy_supervisor_on_timer(ref(self.c), self.now, ref(self.out))
        self._same_actions(actions)

    @rule()
    def restart(self) -> None:
        """A reset: Python keeps its record in memory; C has only what it asked to persist."""
        self.py.power_loss(self.now)
        assert self._load() == (1 if self.nv_counter[0] else 0)
        self.lib.canergy_supervisor_restart(ref(self.c), self.now)

    @rule(amount=st.integers(0, 5_000_000))
    def inject(self, amount: int) -> None:
        code = self.lib.canergy_supervisor_inject(ref(self.c), amount)
        try:
            self.py.inject(amount)
        except LocalProtocolError:
            assert code == ERR_AMOUNT
            return
        assert code == OK
        self._persist()  # supervisor.h: write the record after an injection

    @invariant()
    def same_books(self) -> None:
        st_ = self.py.state
        assert (self.c.usable_uj, self.c.injected_uj) == (st_.usable, st_.injected)
        for i, s in enumerate(st_.sessions):
            assert fields_of(self.c.sessions[i]) == fields_of(self._comparable(s))
        deadline = self.py.get_timer()
        expected = self.lib.CANERGY_NEVER if deadline is None else deadline
        assert self.lib.canergy_supervisor_deadline(ref(self.c)) == expected

    def _comparable(self, s: Session) -> Session:
        return s


TestSideBySide = SideBySide.TestCase
TestSideBySide.settings = settings(max_examples=150, stateful_step_count=60, deadline=None)


class WitnessedSideBySide(SideBySide):
    """The same under the witnessed rules: every reset is a start with a fresh nonce (the C side
    from its NV bytes alone), SYNC re-sent by the timer, the node's books (Rc near Gs or far:
    Us may go below zero) and counts (ltx near tx) with the SYNC's nonce or another; grants
    refused while a start waits and beyond the window. W is volatile: C starts from its bytes
    with W 0, Python keeps it in memory; either is overwritten by the counts before it is used,
    so it is compared from then on."""

    variant = "witnessed"

    @rule(nonce=st.integers(0, 0xFFFF))
    def start(self, nonce: int) -> None:
        self.py.power_loss(self.now, nonce=nonce)
        assert self._load() == (1 if self.nv_counter[0] else 0)
        self.lib.canergy_supervisor_start(ref(self.c), nonce, self.now, ref(self.out))
        if self.out.persist:
            self._persist()

    @rule(data=st.data())
    def sync_answer(self, data: st.DataObject) -> None:
        node = data.draw(st.sampled_from(NODES))
        s = self.py.session(node)
        nonce = data.draw(
            st.sampled_from([s.sync_nonce, s.sync_nonce ^ 1, s.resume_nonce & 0xFFFF])
        )
        if data.draw(st.booleans(), label="books"):
            near = st.integers(-3, 3) | st.integers(-3, 3_000) | st.just(0x7FFFFF)
            rc = s.delivered // QUANTUM_UJ + data.draw(near)
            msg = Debit.books(node, nonce, rc & 0xFFFFFF)
        else:
            ltx = s.tx + data.draw(st.integers(-3, 3) | st.sampled_from([64, 0x7FFF]))
            seq = s.returns_credited + data.draw(st.integers(-2, 2))
            msg = Debit.counts(node, nonce, seq & 0xFFFF, ltx & 0xFFFF)
        frame, _buf = rx(*CODEC.encode(msg), lib=self.lib)
        status = self.lib.canergy_supervisor_on_frame(
            ref(self.c), ref(frame), self.now, ref(self.out)
        )
        assert status == OK
        self._same_actions(self.py.receive(msg, self.now))

    @rule()
    def same_waiting(self) -> None:
        nodes = cbuf(size=len(NODES))
        n = self.lib.canergy_supervisor_unconfirmed(ref(self.c), nodes)
        assert tuple(nodes[0:n]) == self.py.unconfirmed()

    def _comparable(self, s: Session) -> Session:
        if s.phase in SYNC_PHASES:  # W is not used before the counts set it
            return replace(s, witness=0)
        return s


TestWitnessedSideBySide = WitnessedSideBySide.TestCase
TestWitnessedSideBySide.settings = settings(max_examples=150, stateful_step_count=60, deadline=None)


class AgainstTheBrokenBuild(SideBySide):
    """The same machine on the build that credits a duplicated RETURN again."""

    VARIANT = "broken"


def test_the_machine_catches_a_broken_build() -> None:
    with pytest.raises(AssertionError):
        run_state_machine_as_test(
            AgainstTheBrokenBuild,
            settings=settings(
                max_examples=300,
                stateful_step_count=60,
                deadline=None,
                phases=[Phase.explicit, Phase.reuse, Phase.generate],  # found is enough
            ),
        )
