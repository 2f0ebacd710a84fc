"""Hypothesis state machine: one supervisor, three clients, an adversarial channel.

Frames travel as encoded bytes and pass the real codec on delivery, so corruption is caught (or
not) exactly as on a bus. Invariant after every step: the ledger never shows generated energy.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.internal.conjecture import providers
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from canergy.codec import Codec, DecodeError
from canergy.core import Client, LocalProtocolError, Send, Supervisor, Timing
from canergy.core.state import Phase
from canergy.frozen import evolve
from canergy.ledger import ledger, node_overlap
from canergy.messages import Direction, Message, ToClient, ToSupervisor

NODES = (1, 2, 3)
CODEC = Codec()
MAX_IN_FLIGHT = 24
mj = st.integers(1, 3000).map(lambda m: m * 1000)


def _decodes_to_another(arbitration_id: int, damaged: bytes, sent: Message) -> bool:
    try:
        return CODEC.decode(arbitration_id, damaged) != sent
    except DecodeError:
        return False


class Channel(RuleBasedStateMachine):
    variant = "hardened"

    @initialize(initial=st.integers(0, 20_000).map(lambda m: m * 1000))
    def start(self, initial: int) -> None:
        self.timing = Timing(response_timeout_us=10, retries=2, command_timeout_us=25)
        self.sup = Supervisor(NODES, initial, variant=self.variant, timing=self.timing)
        self.clients = {n: Client(n, variant=self.variant, timing=self.timing) for n in NODES}
        self.frames: list[tuple[int, bytes, Message]] = []  # as carried, and as sent
        self.now = 0
        self.decode_errors = 0
        self.undetected = 0

    # -- plumbing ----------------------------------------------------------------------
    def _out(self, actions: list) -> None:
        for a in actions:
            if isinstance(a, Send):
                self.frames.append((*CODEC.encode(a.message), a.message))

    def _deliver(self, arbitration_id: int, data: bytes) -> None:
        try:
            msg: Message = CODEC.decode(arbitration_id, data)
        except DecodeError:
            self.decode_errors += 1
            return
        if msg.TYPE.direction is Direction.TO_CLIENT:
            assert isinstance(msg, ToClient)
            self._out(self.clients[msg.node].receive(msg, self.now))
        else:
            assert isinstance(msg, ToSupervisor)
            self._out(self.sup.receive(msg, self.now))

    # -- the application ---------------------------------------------------------------
    @rule(node=st.sampled_from(NODES), amount=mj)
    def begin(self, node: int, amount: int) -> None:
        s = self.sup.session(node)
        if s.phase is Phase.IDLE and amount <= self.sup.state.usable:
            self._out(self.sup.begin(node, amount, self.now))
        else:
            with pytest.raises(LocalProtocolError):
                self.sup.begin(node, amount, self.now)

    @rule(node=st.sampled_from(NODES), commit=st.booleans())
    def decide(self, node: int, commit: bool) -> None:
        if self.sup.session(node).phase is Phase.ACKED:
            self._out((self.sup.commit if commit else self.sup.abort)(node, self.now))

    @rule(node=st.sampled_from(NODES), fraction=st.floats(0.01, 1.0))
    def spend(self, node: int, fraction: float) -> None:
        c = self.clients[node]
        amount = int(c.state.usable * fraction)
        if amount > 0:
            self._out(c.spend(amount))

    @rule(node=st.sampled_from(NODES), amount=mj)
    def give_back(self, node: int, amount: int) -> None:
        c = self.clients[node]
        if c.can_give_back() and amount <= c.state.usable:
            self._out(c.give_back(amount, self.now))

    @rule(node=st.sampled_from(NODES), amount=mj, commit=st.booleans())
    def nominal_transaction(self, node: int, amount: int, commit: bool) -> None:
        """A whole fault-free exchange at once, so faults can be explored around it."""
        if self.sup.session(node).phase is not Phase.IDLE or amount > self.sup.state.usable:
            return
        self._out(self.sup.begin(node, amount, self.now))
        for _ in range(4):
            self.deliver_all()
            if self.sup.session(node).phase is Phase.ACKED:
                self._out((self.sup.commit if commit else self.sup.abort)(node, self.now))

    @rule()
    def deliver_all(self) -> None:
        """Deliver in order until quiet (bounded: the paper's rules can ping-pong forever)."""
        for _ in range(200):
            if not self.frames:
                return
            self._deliver(*self.frames.pop(0)[:2])

    @rule(amount=mj)
    def inject(self, amount: int) -> None:
        self.sup.inject(amount)

    # -- time and power ----------------------------------------------------------------
    @rule(node=st.sampled_from(NODES))
    def supervisor_timer(self, node: int) -> None:
        deadline = self.sup.session(node).deadline
        if deadline is not None:
            self.now = max(self.now, deadline)
            self._out(self.sup.fire_timer(node, self.now))

    @rule(node=st.sampled_from(NODES), which=st.sampled_from(["command", "return"]))
    def client_timer(self, node: int, which: str) -> None:
        c = self.clients[node]
        deadline = c.state.deadline if which == "command" else c.state.return_deadline
        if deadline is not None:
            self.now = max(self.now, deadline)
            fire = c.fire_command_timer if which == "command" else c.fire_return_timer
            self._out(fire(self.now))

    @rule(us=st.integers(1, 40))
    def wait(self, us: int) -> None:
        self.now += us

    @rule(node=st.sampled_from(NODES))
    def client_power_loss(self, node: int) -> None:
        self.clients[node].power_loss(self.now)

    @rule()
    def supervisor_power_loss(self) -> None:
        self.sup.power_loss(self.now)

    # -- the channel -------------------------------------------------------------------
    @precondition(lambda self: self.frames)
    @rule(i=st.integers(0, MAX_IN_FLIGHT))
    def deliver(self, i: int) -> None:
        self._deliver(*self.frames.pop(i % len(self.frames))[:2])  # any order

    @precondition(lambda self: self.frames)
    @rule(i=st.integers(0, MAX_IN_FLIGHT))
    def lose(self, i: int) -> None:
        self.frames.pop(i % len(self.frames))

    @precondition(lambda self: 0 < len(self.frames) < MAX_IN_FLIGHT)
    @rule(i=st.integers(0, MAX_IN_FLIGHT))
    def duplicate(self, i: int) -> None:
        self.frames.append(self.frames[i % len(self.frames)])

    @precondition(lambda self: self.frames)
    @rule(i=st.integers(0, MAX_IN_FLIGHT), byte=st.integers(0, 7), flip=st.integers(1, 255))
    def corrupt(self, i: int, byte: int, flip: int) -> None:
        """Damage a frame in flight. Damage that still decodes to another valid message (it
        got past the CRC-8, about 1 in 256 multi-byte patterns; on a bus CAN's CRC-15 must miss
        it first) is the residual risk docs/protocol.md bounds, not a fault the protocol
        claims to survive: it is counted and not applied."""
        arbitration_id, data, sent = self.frames[i % len(self.frames)]
        damaged = bytearray(data)
        damaged[byte % len(data)] ^= flip
        if _decodes_to_another(arbitration_id, bytes(damaged), sent):
            self.undetected += 1
            return
        self.frames[i % len(self.frames)] = (arbitration_id, bytes(damaged), sent)

    # -- invariants --------------------------------------------------------------------
    @invariant()
    def passive(self) -> None:
        led = ledger(self.sup.state, [c.state for c in self.clients.values()])
        assert led.dissipated >= 0, f"energy generated: {led}"

    @invariant()
    def timer_is_the_earliest_deadline(self) -> None:
        deadlines = [s.deadline for s in self.sup.state.sessions if s.deadline is not None]
        assert self.sup.get_timer() == (min(deadlines) if deadlines else None)

    @invariant()
    def budgets_never_negative(self) -> None:
        assert self.sup.state.usable >= 0
        for s in self.sup.state.sessions:
            c = self.clients[s.node].state
            assert s.reserved >= 0 and c.usable >= 0 and c.return_pending >= 0
            assert node_overlap(s, c) <= s.reserved
            # no client ever received more than the supervisor released for it
            assert c.credited <= s.delivered + s.reserved


TestHardenedChannel = Channel.TestCase


class StateSetFromOutside(Channel):
    """The same, the supervisor's state also replaced by an equal one that is another object
    (as a gateway or a restore sets it): the deadlines it keeps for its timer follow."""

    @rule()
    def state_set_from_outside(self) -> None:
        self.sup.state = evolve(self.sup.state)


TestStateSetFromOutside = StateSetFromOutside.TestCase


class PaperChannel(Channel):
    variant = "paper"


@pytest.fixture
def no_local_constants(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Hypothesis also draws literals found in the project's modules imported so far, so a
    derandomized search varies with which tests ran before it in the process (this one missed
    the paper's flaw after the bench tests). The pool is emptied for the search's duration:
    the same examples whatever ran before (hypothesis is pinned; its internals may move)."""
    monkeypatch.setattr(providers, "_get_local_constants", providers.Constants)
    providers.CONSTANTS_CACHE.cache.clear()  # entries drawn from the pool so far
    yield
    providers.CONSTANTS_CACHE.cache.clear()


@pytest.mark.usefixtures("no_local_constants")
def test_the_invariant_catches_the_paper_rules() -> None:
    """The same machine on the paper's rules must find generated energy (the check has teeth)."""
    from hypothesis.stateful import run_state_machine_as_test

    with pytest.raises(AssertionError):
        run_state_machine_as_test(
            PaperChannel,
            settings=settings(
                max_examples=3000,
                stateful_step_count=30,
                derandomize=True,
                deadline=None,
                database=None,
                suppress_health_check=list(HealthCheck),
            ),
        )


def test_a_duplicated_return_trips_the_invariant_on_the_paper_rules() -> None:
    """Scripted through the machine's own rules: hazard (c) must fail the passivity check."""
    machine = PaperChannel()
    machine.start(initial=10_000_000)
    machine.nominal_transaction(node=1, amount=2_000_000, commit=True)
    machine.give_back(node=1, amount=1_000_000)
    machine.passive()
    machine.duplicate(i=0)
    machine.deliver_all()
    with pytest.raises(AssertionError, match="energy generated"):
        machine.passive()
