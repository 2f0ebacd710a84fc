"""The Python hardened client and the C client side by side, under the same events.

One Python ``Supervisor`` grants to node 1 over an adversarial channel (loss, duplication,
reordering, corruption); random but valid supervisor messages near the node's own counters are
mixed in (stale, fresh and far intentions, Gs that pay back or would overflow the record, commits,
aborts, return acks, admits for this start and for another); the node spends, gives back, loses
power (both restart from their NV bytes), loses its books (NV wiped) and is torn mid-write.
Every frame reaches both clients as bytes; after every step both must have sent the same frames
byte for byte, asked for the same persist, hold the same NV image byte for byte and the same
state and energy counters.

Profiles: 200 examples of 60 steps by default; ``CANERGY_LONG=1`` runs 2,500 of 120.
tests/test_c_sidebyside.py runs ``SideBySide`` with these settings, tests/test_c_broken.py
``run_side_by_side`` on a deliberately broken C rule.
"""

from __future__ import annotations

import os
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from canergy.codec import Codec, DecodeError
from canergy.core import Action, Client, LocalProtocolError, Persist, Supervisor, Timing
from canergy.core.state import ClientState, Outcome, Phase, Session, SupervisorState
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    COUNTER_END,
    USABLE_MAX_UJ,
    Abort,
    Ack,
    Admit,
    Commit,
    Direction,
    FinalAck,
    Intention,
    Message,
    ReturnAck,
    StatusRequest,
    ToSupervisor,
)
from firmware_model.nvstore import SimulatedPowerLoss
from support.c_binding import (
    ERR_AMOUNT,
    ERR_PHASE,
    OK,
    REASONS,
    RX_OTHER_NODE,
    SLOT,
    CClient,
    CLib,
    Out,
    c_view,
    events_of,
    frames_of,
    library,
    out_frames,
)
from support.mem_nv import MemNv, write_slot

NODE = 1
CODEC = Codec()
TIMING = Timing(response_timeout_us=10, retries=2, command_timeout_us=25, return_retry_us=30)
MAX_IN_FLIGHT = 16
LONG = os.environ.get("CANERGY_LONG") == "1"
SETTINGS = settings(
    max_examples=2500 if LONG else int(os.environ.get("CANERGY_SIDE_BY_SIDE_EXAMPLES", "200")),
    stateful_step_count=120 if LONG else 60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
USABLE_ROOM_MJ = 4_294_967  # Gs this far ahead would overflow an empty record


BOOKS = st.builds(
    ClientState,
    st.just(NODE),
    usable=st.integers(0, 50_000_000) | st.integers(USABLE_MAX_UJ - 70_000_000, USABLE_MAX_UJ),
    credited=st.integers(0, 2**32 - 1).map(lambda mj: mj * 1000),
    spent=st.integers(0, 2**40),
    last_tx=st.integers(0, COUNTER_BOUND - 1)
    | st.integers(COUNTER_END - 5, COUNTER_END + 1)  # the end of the numbering
    | st.just(COUNTER_BOUND - 1),
    outcome=st.sampled_from(list(Outcome)[0:4]),
    return_seq=st.integers(0, COUNTER_BOUND - 1)
    | st.integers(0xFFFB, 0x10004)
    | st.integers(COUNTER_END - 4, COUNTER_END)
    | st.just(COUNTER_BOUND - 1),
)
"""A record to start from; the supervisor's books for the node then agree with it."""


class SideBySide(RuleBasedStateMachine):
    lib: CLib | None = None  # None: the tested library; a subclass may break it

    @initialize(
        initial_mj=st.integers(0, 40_000),
        nonce=st.integers(0, 0xFFFF),
        books=st.none() | BOOKS,
    )
    def start(self, initial_mj: int, nonce: int, books: ClientState | None) -> None:
        """A node without books (it JOINs), or one with a record: then the supervisor's books
        for it agree with that record (same tx, Gs = Rc, returns credited)."""
        self.now = 0
        self.resets = 0
        session = Session(NODE)
        if books is not None:
            session = Session(
                NODE, tx=books.last_tx, delivered=books.credited, returns_credited=books.return_seq
            )
        state = SupervisorState(initial_mj * 1000, initial_mj * 1000, 0, (session,))
        self.sup = self._new_supervisor(state)
        self.to_client: list[tuple[int, bytes]] = []
        self.to_sup: list[tuple[int, bytes]] = []
        self.py_raw = bytearray()
        if books is not None:
            self._store(self.py_raw).save(books)
        self.c_raw = bytearray(self.py_raw)
        self.tear_next = False
        self.c = self._new_client()
        self.py: Client
        self._boot(nonce)

    # -- what a subclass with other rules replaces ------------------------------------------
    def _new_supervisor(self, state: SupervisorState) -> Supervisor:
        return Supervisor([NODE], state.initial, timing=TIMING, state=state)

    def _new_client(self) -> CClient:
        return CClient(NODE, timing=TIMING, lib=self.lib or library())

    def _store(self, raw: bytearray) -> MemNv:
        return MemNv(raw)

    def _py_spend(self, amount: int) -> list[Action]:
        return self.py.spend(amount)

    def _c_spend(self, amount: int) -> int:
        return self.c.do_spend(amount)

    def _may_begin(self, s: Session) -> bool:
        """Whether the rules let the supervisor begin now, beyond phase, Us and the end."""
        return True

    # -- comparing one step ---------------------------------------------------------------
    def _carry_out(self, actions: list[Action], out: Out) -> None:
        """Both sides did one step: same frames, notes and persist; write NV; send once."""
        assert out_frames(out) == frames_of(CODEC, actions), "frames differ"
        assert out.events & 0x3F == events_of(actions), "notes differ"
        persists = [i for i, a in enumerate(actions) if isinstance(a, Persist)]
        assert persists in ([], [0]), "Python asked to persist after a send"
        assert bool(out.persist) == bool(persists), "persist differs"
        if persists:
            if self.tear_next:
                self._torn_write(out)
                return
            self.py_store.save(self.py.state)
            write_slot(self.c_raw, out.nv_slot, bytes(out.nv_image))
        for arbitration_id, data in out_frames(out):
            if len(self.to_sup) < MAX_IN_FLIGHT:
                self.to_sup.append((arbitration_id, data))
        self._same()

    def _torn_write(self, out: Out) -> None:
        """The power fails half way through this write: neither side sends anything, both boot
        again from what the half-written NV holds."""
        self.tear_next = False
        self.py_store.crash_after = self.py_store.stats.writes + 1
        try:
            self.py_store.save(self.py.state)
            raise AssertionError("NvStore did not tear the write")
        except SimulatedPowerLoss:
            pass
        write_slot(self.c_raw, out.nv_slot, bytes(out.nv_image)[0 : SLOT // 2])
        assert self.py_raw == self.c_raw, "torn images differ"
        self._boot(0x5A5A)

    def _same(self) -> None:
        assert self.c.view() == c_view(self.py.state), "states differ"
        assert self.py_raw == self.c_raw, "NV images differ"

    def _boot(self, nonce: int) -> None:
        """Power on: both restart from their NV bytes, as firmware_model's node does."""
        self.py_store = self._store(self.py_raw)
        record = self.py_store.load()
        self.py = Client(NODE, timing=TIMING, state=record or ClientState(NODE))
        self.py.power_loss(self.now)
        actions = [] if record is not None else self.py.books_lost(nonce, self.now)
        fallbacks = self.c.start(bytes(self.c_raw), nonce, self.now)
        assert fallbacks == self.py_store.stats.fallbacks, "NV load differs"
        self._carry_out(actions, self.c.out)

    def _to_client(self, arbitration_id: int, data: bytes) -> None:
        """One frame off the bus into both clients."""
        try:
            msg = CODEC.decode(arbitration_id, data, direction=Direction.TO_CLIENT)
        except DecodeError as err:
            out = self.c.frame(arbitration_id, data, self.now)
            assert REASONS.get(self.c.last_status) is err.reason, "decode differs"
            assert out_frames(out) == [] and not out.persist
            return
        out = self.c.frame(arbitration_id, data, self.now)
        actions = self.py.receive(msg, self.now)  # type: ignore[arg-type]
        assert self.c.last_status == (OK if msg.node == NODE else RX_OTHER_NODE)
        self._carry_out(actions, out)

    def _queue(self, msg: Message) -> None:
        if len(self.to_client) < MAX_IN_FLIGHT:
            self.to_client.append(CODEC.encode(msg))

    def _sup_out(self, actions: list[Action]) -> None:
        for frame in frames_of(CODEC, actions):
            if len(self.to_client) < MAX_IN_FLIGHT:
                self.to_client.append(frame)

    # -- the supervisor ---------------------------------------------------------------------
    @rule(amount_mj=st.integers(1, 3000))
    def begin(self, amount_mj: int) -> None:
        s = self.sup.session(NODE)
        room = s.tx + 1 < COUNTER_END  # else refused (tests/test_counters_end.py)
        usable = amount_mj * 1000 <= self.sup.state.usable
        if s.phase is Phase.IDLE and usable and room and self._may_begin(s):
            self._sup_out(self.sup.begin(NODE, amount_mj * 1000, self.now))

    @rule(commit=st.booleans())
    def decide(self, commit: bool) -> None:
        if self.sup.session(NODE).phase is Phase.ACKED:
            self._sup_out((self.sup.commit if commit else self.sup.abort)(NODE, self.now))

    @rule(amount_mj=st.integers(1, 3000), commit=st.booleans())
    def nominal_transaction(self, amount_mj: int, commit: bool) -> None:
        """A whole exchange when nothing is in the way, so faults can be explored around it."""
        self.begin(amount_mj)
        for _ in range(4):
            self.deliver_all()
            self.decide(commit)

    @rule()
    def supervisor_timer(self) -> None:
        deadline = self.sup.session(NODE).deadline
        if deadline is not None:
            self.now = max(self.now, deadline)
            self._sup_out(self.sup.fire_timer(NODE, self.now))

    @rule()
    def supervisor_power_loss(self) -> None:
        self.sup.power_loss(self.now)

    # -- messages no supervisor of ours sent: near the node's counters, or far --------------
    @rule(data=st.data())
    def inject(self, data: st.DataObject) -> None:
        p = self.py.state
        near = st.integers(-3, 5) | st.sampled_from([0x7FFF, 0x8000, -0x8000, 0x1234])
        tx = (p.last_tx + data.draw(near)) & 0xFFFF
        amount = data.draw(st.integers(1, 3000) | st.just(AMOUNT_MAX_MJ))
        kind = data.draw(
            st.sampled_from(["int", "int", "commit", "abort", "retack", "admit", "other"])
        )
        msg: Message
        if kind == "int":
            paid = data.draw(
                st.integers(-3, 3000)
                | st.sampled_from([USABLE_ROOM_MJ, USABLE_ROOM_MJ + 1, 0x7FFFFF, -0x800000])
            )
            msg = Intention(NODE, tx, amount, (p.credited // 1000 + paid) & 0xFFFFFF)
        elif kind in ("commit", "abort"):
            if p.phase is Phase.AWAIT_COMMAND and data.draw(st.booleans()):
                tx = p.held_tx & 0xFFFF
            msg = (Commit if kind == "commit" else Abort)(NODE, tx, amount)
        elif kind == "retack":
            msg = ReturnAck(NODE, (p.return_seq + data.draw(st.integers(-1, 1))) & 0xFFFF)
        elif kind == "admit":
            nonce = p.nonce if data.draw(st.booleans()) else data.draw(st.integers(0, 0xFFFF))
            msg = Admit(
                NODE, nonce, data.draw(st.integers(0, 0xFFFF)), data.draw(st.integers(0, 0xFFFF))
            )
        else:
            msg = data.draw(
                st.sampled_from(
                    [
                        StatusRequest(NODE, tx),
                        FinalAck(NODE, tx),
                        Intention(2, tx, amount, 0),
                        Ack(NODE, tx),
                    ]
                )
            )
        self._queue(msg)

    # -- the channel ----------------------------------------------------------------------------
    @precondition(lambda self: self.to_client)
    @rule(i=st.integers(0, MAX_IN_FLIGHT))
    def deliver_to_client(self, i: int) -> None:
        self._to_client(*self.to_client.pop(i % len(self.to_client)))

    @precondition(lambda self: self.to_sup)
    @rule(i=st.integers(0, MAX_IN_FLIGHT))
    def deliver_to_supervisor(self, i: int) -> None:
        arbitration_id, data = self.to_sup.pop(i % len(self.to_sup))
        msg = CODEC.decode(arbitration_id, data)
        assert isinstance(msg, ToSupervisor)  # TELEMETRY never comes from a client alone
        self._sup_out(self.sup.receive(msg, self.now))

    @rule()
    def deliver_all(self) -> None:
        for _ in range(40):
            if self.to_sup:
                self.deliver_to_supervisor(0)
            elif self.to_client:
                self.deliver_to_client(0)
            else:
                return

    @precondition(lambda self: self.to_client or self.to_sup)
    @rule(i=st.integers(0, MAX_IN_FLIGHT), to_client=st.booleans())
    def lose(self, i: int, to_client: bool) -> None:
        queue = self.to_client if (to_client and self.to_client) or not self.to_sup else self.to_sup
        queue.pop(i % len(queue))

    @precondition(lambda self: 0 < len(self.to_client) < MAX_IN_FLIGHT)
    @rule(i=st.integers(0, MAX_IN_FLIGHT))
    def duplicate(self, i: int) -> None:
        self.to_client.append(self.to_client[i % len(self.to_client)])

    @precondition(lambda self: self.to_client)
    @rule(
        i=st.integers(0, MAX_IN_FLIGHT),
        byte=st.integers(0, 7),
        flip=st.integers(1, 255),
        relabel=st.sampled_from([0, 0, 0, 1, 0x100, 0x800, 0x1000]),
    )
    def corrupt(self, i: int, byte: int, flip: int, relabel: int) -> None:
        k = i % len(self.to_client)
        arbitration_id, data = self.to_client[k]
        damaged = bytearray(data)
        damaged[byte % len(data)] ^= flip
        self.to_client[k] = (arbitration_id ^ relabel, bytes(damaged))

    # -- time, the actuator, the return channel, power ------------------------------------------
    @rule(us=st.integers(1, 40))
    def wait(self, us: int) -> None:
        self.now += us

    @rule(jump=st.booleans())
    def client_timers(self, jump: bool) -> None:
        deadline = self.py.get_timer()
        assert self.c.get_timer() == deadline, "deadlines differ"
        if jump and deadline is not None:
            self.now = max(self.now, deadline)
        out = self.c.timers(self.now)
        self._carry_out(self.py.handle_timer(self.now), out)

    @rule(fraction=st.floats(0, 1.2), exact=st.sampled_from([None, 0, 1, -1]))
    def spend(self, fraction: float, exact: int | None) -> None:
        usable = self.py.state.usable
        amount = int(usable * fraction) if exact is None else max(0, usable + exact)
        code = self._c_spend(amount) if amount <= 0xFFFF_FFFF else ERR_AMOUNT  # u32 API
        try:
            actions = self._py_spend(amount)
        except LocalProtocolError:
            assert code in (ERR_AMOUNT, ERR_PHASE), f"C spent {amount} where Python refused"
            self._same()
            return
        assert code == OK, f"C refused to spend {amount}"
        self._carry_out(actions, self.c.out)

    @rule(
        amount=st.integers(1, 3000).map(lambda m: m * 1000)
        | st.sampled_from([0, 1500, AMOUNT_MAX_MJ * 1000, AMOUNT_MAX_MJ * 1000 + 1000])
    )
    def give_back(self, amount: int) -> None:
        code = self.c.do_give_back(amount, self.now)
        try:
            actions = self.py.give_back(amount, self.now)
        except LocalProtocolError:
            assert code in (ERR_AMOUNT, ERR_PHASE), f"C gave back {amount} where Python refused"
            self._same()
            return
        assert code == OK, f"C refused to give back {amount}"
        self._carry_out(actions, self.c.out)

    # Power events are capped per example: each one wipes the volatile state, and a run that
    # reboots every few steps never gets far enough to reach pay-backs and return acks.
    @precondition(lambda self: self.resets < 4)
    @rule(nonce=st.integers(0, 0xFFFF))
    def power_loss(self, nonce: int) -> None:
        self.resets += 1
        self._boot(nonce)

    @precondition(lambda self: self.resets < 2)
    @rule(nonce=st.integers(0, 0xFFFF))
    def books_lost(self, nonce: int) -> None:
        self.resets += 1
        self.py_raw.clear()
        self.c_raw.clear()
        self._boot(nonce)

    @precondition(lambda self: self.resets < 3 and not self.tear_next)
    @rule()
    def tear_the_next_write(self) -> None:
        self.resets += 1
        self.tear_next = True

    @invariant()
    def same_books(self) -> None:
        self._same()


def run_side_by_side(machine: type[SideBySide], **overrides: Any) -> None:
    from hypothesis.stateful import run_state_machine_as_test

    run_state_machine_as_test(machine, settings=settings(SETTINGS, **overrides))
