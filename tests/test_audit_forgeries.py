"""canergy audit against a hostile bus participant: each forgery is flagged, naming the forged
frame and no genuine one, and honest captures with faults raise no alarm.

Honest traffic comes from the real protocol cores on one simulated CAN bus in virtual time:
every frame sent is on the bus (the capture), each receiver may miss it, some frames go out
twice, nodes and the supervisor lose power, a node may lose its books (JOIN/ADMIT). The forger
puts frames built with the public codec on the same bus, and the cores react to them.
"""

from __future__ import annotations

import json
import random
from collections import deque
from pathlib import Path

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.cli import main
from canergy.codec import Codec
from canergy.core import Acknowledged, Action, Client, Send, Supervisor, Timing
from canergy.core.state import Phase
from canergy.demo import DemoConfig, run_demo
from canergy.faults import FaultProfile
from canergy.inspect.audit import Auditor
from canergy.inspect.captures import read_file
from canergy.inspect.frames import describe
from canergy.messages import (
    AMOUNT_MAX_MJ,
    QUANTUM_UJ,
    Commit,
    Direction,
    Intention,
    Message,
    Return,
    ReturnAck,
    ToClient,
    ToSupervisor,
)
from canergy.seqnum import wrap

CODEC = Codec()
MJ = QUANTUM_UJ
TICK_US = 10_000
FRAME_US = 200
DATA = Path(__file__).parent / "data"


class Bus:
    """A supervisor and clients (real cores) on one bus; ``frames`` is the capture."""

    def __init__(
        self,
        nodes: tuple[int, ...] = (1, 2),
        *,
        seed: int = 0,
        loss: float = 0.05,
        duplicate: float = 0.03,
        resets: float = 0.0,
        nv_losses: float = 0.0,
        commit_ratio: float = 0.8,
    ) -> None:
        self.rng = random.Random(seed)
        self.timing = Timing()
        self.sup = Supervisor(nodes, 10_000 * MJ, timing=self.timing)
        self.sups: list[Supervisor] = [self.sup]
        self.clients = {n: Client(n, timing=self.timing) for n in nodes}
        self.loss, self.duplicate, self.resets, self.nv_losses = loss, duplicate, resets, nv_losses
        self.commit_ratio = commit_ratio
        self.frames: list[can.Message] = []
        self.forged: list[int] = []
        self.queue: deque[tuple[Message, Supervisor | None, bool]] = deque()
        self.away = False
        self.now = 0

    # -- the bus ----------------------------------------------------------------------------
    def _put(self, msg: Message, origin: Supervisor | None, forged: bool) -> None:
        copies = 2 if not forged and self.rng.random() < self.duplicate else 1
        for _ in range(copies):
            self.queue.append((msg, origin, forged))
        if len(self.queue) == copies:
            self._pump()

    def _pump(self) -> None:
        while self.queue:
            msg, origin, forged = self.queue[0]
            self.now += FRAME_US
            ident, data = CODEC.encode(msg)
            self.frames.append(
                can.Message(timestamp=self.now / 1e6, arbitration_id=ident, data=data)
            )
            if forged:
                self.forged.append(len(self.frames))
            heard = forged or self.rng.random() >= self.loss  # the forger's frames arrive
            if msg.TYPE.direction is Direction.TO_CLIENT:
                assert isinstance(msg, ToClient)
                if heard:
                    self._act(self.clients[msg.node].receive(msg, self.now), None)
            else:
                assert isinstance(msg, ToSupervisor)
                for sup in self._listening():
                    if sup is not origin and heard:
                        self._act(sup.receive(msg, self.now), sup)
            self.queue.popleft()

    def _listening(self) -> list[Supervisor]:
        return [s for s in self.sups if not (self.away and s is self.sup)]

    def _act(self, actions: list[Action], sup: Supervisor | None) -> None:
        for a in actions:
            if isinstance(a, Send):
                self._put(a.message, sup, forged=sup is not None and sup is not self.sup)
            elif isinstance(a, Acknowledged) and sup is not None:
                decide = sup.commit if self.rng.random() < self.commit_ratio else sup.abort
                self._act(decide(a.node, self.now), sup)

    def forge(self, msg: Message) -> int:
        """Put a forged frame on the bus; its 1-based index in the capture."""
        self._put(msg, None, forged=True)
        return self.forged[-1]

    # -- time and workload ------------------------------------------------------------------
    def run(self, duration_us: int, *, grants: bool = True, returns: bool = True) -> None:
        end = self.now + duration_us
        while self.now < end:
            self._tick(grants, returns)
            next_tick = self.now + TICK_US
            while (due := self._next_timer()) is not None and due < next_tick:
                self.now = max(self.now, due)
                for sup in self._listening():
                    self._act(sup.handle_timer(self.now), sup)
                for c in self.clients.values():
                    self._act(c.handle_timer(self.now), None)
            self.now = max(self.now, next_tick)

    def _next_timer(self) -> int | None:
        timers = [s.get_timer() for s in self._listening()]
        timers += [c.get_timer() for c in self.clients.values()]
        due = [t for t in timers if t is not None]
        return min(due) if due else None

    def _tick(self, grants: bool, returns: bool) -> None:
        rng = self.rng
        for n, c in self.clients.items():
            if c.state.usable:
                c.spend(min(c.state.usable, rng.randint(1, 3) * MJ))
            if returns and rng.random() < 0.03:
                self.give_back(n, c.state.usable // 2)
            if rng.random() < self.resets:
                c.power_loss(self.now)
            if rng.random() < self.nv_losses:
                self._act(c.books_lost(rng.getrandbits(16), self.now), None)
        if not self.away and rng.random() < self.resets:
            self.sup.power_loss(self.now)
        if grants:
            for sup in self._listening():
                for n in sup.nodes:
                    if sup.session(n).phase is Phase.IDLE and sup.state.usable >= 60 * MJ:
                        self._act(sup.begin(n, rng.randint(10, 60) * MJ, self.now), sup)

    def give_back(self, node: int, amount: int) -> None:
        amount = min(amount - amount % MJ, AMOUNT_MAX_MJ * MJ)
        c = self.clients[node]
        if amount > 0 and c.can_give_back():
            self._act(c.give_back(amount, self.now), None)

    def idle(self, node: int = 1) -> None:
        """Run on without new grants until the supervisor has no open transaction for node."""
        for _ in range(200):
            if self.sup.session(node).phase is Phase.IDLE:
                return
            self.run(TICK_US, grants=False)
        raise AssertionError("the transaction never ended")

    def gs_mj(self, node: int = 1) -> int:
        return self.sup.session(node).delivered // MJ

    def tx(self, node: int = 1) -> int:
        return self.sup.session(node).tx

    # -- the audit --------------------------------------------------------------------------
    def audit(self) -> Auditor:
        auditor = Auditor()
        for frame in self.frames:
            auditor.feed(describe(CODEC, frame))
        auditor.finish()
        return auditor


def flagged(bus: Bus) -> list[int]:
    return sorted({v.frame for v in bus.audit().violations})


def test_an_honest_bus_is_clean() -> None:
    bus = Bus(seed=1)
    bus.run(2_000_000)
    assert len(bus.frames) > 500
    assert flagged(bus) == []


# -- the seven forgeries ----------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(3))
def test_1_commit_without_intention(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000)
    bus.idle()
    forged = bus.forge(Commit(1, wrap(bus.tx() + 1, 16), AMOUNT_MAX_MJ))
    assert bus.clients[1].state.last_tx == bus.tx() + 1, "the node took it"
    bus.run(1_000_000)
    assert flagged(bus) == [forged]


@pytest.mark.parametrize("seed", range(3))
def test_2_intention_never_decided_is_timeout_committed(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000)
    bus.idle()
    credited = bus.clients[1].state.credited
    forged = bus.forge(Intention(1, wrap(bus.tx() + 1, 16), AMOUNT_MAX_MJ, bus.gs_mj()))
    bus.run(300_000, grants=False)  # no COMMIT/ABORT: the node commits by timeout
    assert bus.clients[1].state.credited == credited + AMOUNT_MAX_MJ * MJ
    bus.run(1_000_000)
    assert flagged(bus) == [forged]


@pytest.mark.parametrize("seed", range(3))
def test_3_intention_with_inflated_gs(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000)
    bus.idle()
    credited = bus.clients[1].state.credited
    forged = bus.forge(Intention(1, wrap(bus.tx() + 1, 16), 1, bus.gs_mj() + 4_000_000))
    assert bus.clients[1].state.credited >= credited + 4_000_000 * MJ, "paid back at once"
    bus.run(1_000_000)
    assert flagged(bus) == [forged]


@pytest.mark.parametrize("seed", range(3))
def test_4_return_beyond_what_the_node_holds(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000)
    c = bus.clients[1]
    while not c.can_give_back():
        bus.run(TICK_US)
    usable = bus.sup.state.usable
    forged = bus.forge(Return(1, wrap(c.state.return_seq + 1, 16), AMOUNT_MAX_MJ))
    assert bus.sup.state.usable == usable + AMOUNT_MAX_MJ * MJ
    bus.run(1_000_000)
    assert flagged(bus) == [forged]


def test_5a_return_ack_while_the_supervisor_is_away() -> None:
    bus = Bus(seed=4)
    bus.run(500_000)
    c = bus.clients[1]
    while not c.can_give_back() or c.state.usable < 600 * MJ:
        bus.run(TICK_US)
    bus.idle()
    bus.away = True
    bus.give_back(1, 500 * MJ)
    bus.run(250_000, grants=False)  # the node re-sends its RETURN, nobody answers
    forged = bus.forge(ReturnAck(1, wrap(c.state.return_seq, 16)))
    assert c.can_give_back(), "the node believes its return was credited"
    bus.away = False
    bus.sup.power_loss(bus.now)
    bus.run(200_000, returns=False)
    bus.give_back(1, 10 * MJ)  # the supervisor never credited the previous one: this starves
    bus.run(1_500_000, returns=False)
    assert not c.can_give_back()
    assert flagged(bus) == [forged]


@pytest.mark.parametrize("seed", range(3))
def test_5b_small_return_sent_ahead_of_the_real_one(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000)
    c = bus.clients[1]
    while not c.can_give_back() or c.state.usable < 600 * MJ:
        bus.run(TICK_US)
    usable = bus.sup.state.usable
    forged = bus.forge(Return(1, wrap(c.state.return_seq + 1, 16), 1))
    bus.give_back(1, 500 * MJ)  # counted as a duplicate: 0.5 J vanish
    assert bus.sup.state.usable == usable + 1 * MJ
    bus.run(1_000_000)
    assert flagged(bus) == [forged]


@pytest.mark.parametrize("seed", range(3))
def test_6_intention_far_ahead_of_the_sequence(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000)
    bus.idle()
    forged = bus.forge(Intention(1, wrap(bus.tx() + 30_000, 16), AMOUNT_MAX_MJ, bus.gs_mj()))
    bus.run(1_500_000)
    assert bus.clients[1].state.last_tx >= 30_000, "the node now ignores every real intention"
    assert flagged(bus) == [forged]


@pytest.mark.parametrize("seed", range(3))
def test_7_a_second_supervisor_on_the_same_nodes(seed: int) -> None:
    bus = Bus(seed=seed)
    bus.run(500_000, returns=False)
    bus.sups.append(Supervisor(bus.sup.nodes, 10_000 * MJ, timing=bus.timing))
    bus.run(1_000_000, returns=False)
    assert len(bus.forged) > 10
    assert flagged(bus) == bus.forged


# -- no false alarms ---------------------------------------------------------------------------


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    loss=st.sampled_from([0.0, 0.1, 0.3]),
    resets=st.sampled_from([0.0, 0.01]),
    nv_losses=st.sampled_from([0.0, 0.003]),
    commit_ratio=st.sampled_from([0.0, 0.8, 1.0]),
)
def test_honest_captures_with_faults_raise_no_alarm(
    seed: int, loss: float, resets: float, nv_losses: float, commit_ratio: float
) -> None:
    bus = Bus(
        (1, 2, 3),
        seed=seed,
        loss=loss,
        duplicate=0.05,
        resets=resets,
        nv_losses=nv_losses,
        commit_ratio=commit_ratio,
    )
    bus.run(1_500_000)
    assert bus.audit().violations == []


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("reorder", [0.0, 0.05])
def test_demo_captures_with_faults_raise_no_alarm(
    tmp_path: Path, seed: int, reorder: float
) -> None:
    log = tmp_path / "demo.log"
    faults = FaultProfile(loss=0.3, duplicate=0.05, reorder=reorder, corrupt=0.01)
    cfg = DemoConfig(nodes=(1, 2, 3), transactions=100, faults=faults, seed=seed, resets=4, log=log)
    run_demo(cfg)
    auditor = Auditor(initial=cfg.initial, reordered=reorder > 0)
    for frame in read_file(log, lambda *a: None):
        auditor.feed(describe(CODEC, frame))
    auditor.finish()
    assert auditor.violations == []


def test_the_cli_names_the_forged_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bus = Bus(seed=2)
    bus.run(300_000)
    bus.idle()
    forged = bus.forge(Intention(1, wrap(bus.tx() + 30_000, 16), AMOUNT_MAX_MJ, bus.gs_mj()))
    bus.run(300_000)
    path = tmp_path / "forged.log"
    with can.Logger(str(path)) as writer:
        for frame in bus.frames:
            writer.on_message_received(frame)
    assert main(["audit", str(path), "--json"]) == 1
    (violation,) = json.loads(capsys.readouterr().out)["violations"]
    assert violation["frame"] == forged and violation["node"] == 1
    assert "jumps" in violation["what"]


def test_decode_with_audit_marks_the_forged_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`canergy decode --audit` (and `dump --audit`, the same code) puts the audit's verdict
    under the frame it flags: here a COMMIT for a transaction never intended."""
    from canergy.messages import Ack, Commit, Committed, Intention

    codec = Codec()
    honest = [Intention(1, 1, 500, 0), Ack(1, 1), Commit(1, 1, 500), Committed(1, 1)]
    path = tmp_path / "c.log"
    with can.Logger(str(path)) as log:
        for i, msg in enumerate([*honest, Commit(1, 2, 65535)]):
            arbitration_id, data = codec.encode(msg)
            frame = can.Message(arbitration_id=arbitration_id, data=data, timestamp=1e9 + i)
            frame.channel = "vcan0"
            log.on_message_received(frame)
    capsys.readouterr()
    assert main(["decode", str(path), "--audit", "--color", "never"]) == 0
    lines = capsys.readouterr().out.splitlines()
    flagged = [i for i, text in enumerate(lines) if text.startswith("!!")]
    assert flagged == [len(lines) - 1] and "COMMIT" in lines[-2] and "65.535" in lines[-2]
    assert main(["decode", str(path), "--color", "never"]) == 0  # without --audit: no verdicts
    assert not any(t.startswith("!!") for t in capsys.readouterr().out.splitlines())
