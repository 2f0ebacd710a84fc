"""``canergy demo``: a supervisor and several clients on python-can's virtual bus, under faults.

Runs in virtual time (no sleeping), so a seed reproduces the run exactly. The observer checks the
conservation ledger after every event and remembers the lowest dissipation seen.
"""

from __future__ import annotations

import random
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from canergy.codec import Codec, DecodeError
from canergy.core import (
    Acknowledged,
    Action,
    Client,
    ClientAborted,
    ClientCommitted,
    Credited,
    Resolved,
    Send,
    Supervisor,
    Timing,
)
from canergy.core.state import Outcome, Phase
from canergy.faults import FaultInjector, FaultProfile
from canergy.ledger import Ledger, ledger
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, Direction, ToClient, ToSupervisor
from canergy.units import UJ_PER_J
from canergy.virtual_net import Endpoint, VirtualNetwork

TICK_US = 10_000


@dataclass(frozen=True, slots=True)
class DemoConfig:
    nodes: tuple[int, ...] = (1, 2, 3, 4, 5)
    transactions: int = 200
    duration_s: float = 300.0
    initial: int = 10 * UJ_PER_J
    variant: str = "hardened"
    faults: FaultProfile = field(default_factory=FaultProfile)
    seed: int = 0
    resets: int = 2
    commit_ratio: float = 0.8
    log: Path | None = None
    timing: Timing = field(default_factory=Timing)


@dataclass(slots=True)
class NodeStats:
    committed: int = 0
    aborted: int = 0
    timeout_committed: int = 0
    credited_back: int = 0
    returns: int = 0
    resets: int = 0
    decode_errors: int = 0


@dataclass(slots=True)
class DemoResult:
    config: DemoConfig
    ledger: Ledger
    min_dissipated: int
    first_violation_us: int | None
    nodes: dict[int, NodeStats]
    client_usable: dict[int, int]
    client_spent: dict[int, int]
    outcomes: dict[str, int]
    transactions_started: int
    frames_sent: int
    decode_errors: int
    supervisor_resets: int
    virtual_us: int
    finished: bool
    injector: FaultInjector

    @property
    def passive(self) -> bool:
        return self.min_dissipated >= 0

    def as_json(self) -> dict[str, Any]:
        c = self.injector.counters
        return {
            **self.ledger.as_json(),
            "passive": self.passive,
            "min_dissipated_uj": self.min_dissipated,
            "first_violation_s": (
                None if self.first_violation_us is None else self.first_violation_us / 1e6
            ),
            "variant": self.config.variant,
            "seed": self.config.seed,
            "nodes": {
                str(n): {
                    "usable_uj": self.client_usable[n],
                    "spent_uj": self.client_spent[n],
                    "committed": s.committed,
                    "aborted": s.aborted,
                    "timeout_committed": s.timeout_committed,
                    "credited_back": s.credited_back,
                    "returns": s.returns,
                    "resets": s.resets,
                    "decode_errors": s.decode_errors,
                }
                for n, s in self.nodes.items()
            },
            "transactions_started": self.transactions_started,
            "supervisor_outcomes": self.outcomes,
            "supervisor_resets": self.supervisor_resets,
            "frames_sent": self.frames_sent,
            "frames_lost": c.lost,
            "frames_duplicated": c.duplicated,
            "frames_reordered": c.reordered,
            "frames_corrupted": c.corrupted,
            "decode_errors": self.decode_errors,
            "virtual_seconds": self.virtual_us / 1e6,
            "finished": self.finished,
        }


class _Demo:
    """One run: the nodes, the network, the workload and the observer."""

    def __init__(self, cfg: DemoConfig) -> None:
        self.cfg = cfg
        self.rng = random.Random(cfg.seed)
        self.codec = Codec()
        injector = FaultInjector(cfg.faults, random.Random(f"faults-{cfg.seed}"))
        self.net = VirtualNetwork(self.codec, injector, log=cfg.log, epoch=time.time())
        self.sup = Supervisor(cfg.nodes, cfg.initial, variant=cfg.variant, timing=cfg.timing)
        self.sup_ep = self.net.endpoint("supervisor", self.codec.supervisor_filters())
        self.clients = {n: Client(n, variant=cfg.variant, timing=cfg.timing) for n in cfg.nodes}
        self.client_eps = {
            n: self.net.endpoint(f"node {n}", self.codec.client_filters(n)) for n in cfg.nodes
        }
        self.power_uj_per_tick = {n: self.rng.randint(1, 5) * 1000 for n in cfg.nodes}
        self.stats = {n: NodeStats() for n in cfg.nodes}
        self.outcomes = {o.name.lower(): 0 for o in Outcome if o is not Outcome.NONE}
        self.started = 0
        self.sup_resets = 0
        self.decode_errors = 0
        self.now = 0
        self.min_dissipated = cfg.initial
        self.first_violation: int | None = None
        # grants average half the initial budget spread over all transactions
        self.grant_uj = max(2 * QUANTUM_UJ, cfg.initial // (2 * max(cfg.transactions, 1)))
        # power losses strike after randomly chosen transaction starts
        points = range(1, max(cfg.transactions, 2))
        self.reset_points = sorted(self.rng.choices(points, k=cfg.resets))

    # -- observer ------------------------------------------------------------------------
    def ledger(self) -> Ledger:
        return ledger(self.sup.state, (c.state for c in self.clients.values()))

    def observe(self) -> None:
        d = self.ledger().dissipated
        if d < self.min_dissipated:
            self.min_dissipated = d
        if d < 0 and self.first_violation is None:
            self.first_violation = self.now

    # -- actions -------------------------------------------------------------------------
    def carry_out(self, ep: Endpoint, actions: Iterable[Action]) -> None:
        for a in actions:
            if isinstance(a, Send):
                self.net.send(ep, a.message, self.now)
            elif isinstance(a, Acknowledged):
                decide = (
                    self.sup.commit if self.rng.random() < self.cfg.commit_ratio else self.sup.abort
                )
                self.carry_out(ep, decide(a.node, self.now))
            elif isinstance(a, Resolved):
                self.outcomes[a.outcome.name.lower()] += 1
            elif isinstance(a, ClientCommitted):
                st = self.stats[a.node]
                st.committed += 1
                st.timeout_committed += a.by_timeout
            elif isinstance(a, ClientAborted):
                self.stats[a.node].aborted += 1
            elif isinstance(a, Credited):
                self.stats[a.node].credited_back += 1

    def receive(self, ep: Endpoint, frame: can.Message) -> None:
        to_client = ep is not self.sup_ep
        direction = Direction.TO_CLIENT if to_client else Direction.TO_SUPERVISOR
        node = int(ep.name.split()[-1]) if to_client else None
        try:
            msg = self.codec.decode(
                frame.arbitration_id,
                frame.data,
                extended=frame.is_extended_id,
                remote=frame.is_remote_frame,
                direction=direction,
            )
        except DecodeError:
            self.decode_errors += 1
            if node is not None:
                self.stats[node].decode_errors += 1
            return
        if node is not None:
            assert isinstance(msg, ToClient)
            self.carry_out(ep, self.clients[node].receive(msg, self.now))
        elif isinstance(msg, ToSupervisor):  # demo clients send no telemetry
            self.carry_out(ep, self.sup.receive(msg, self.now))

    # -- workload ------------------------------------------------------------------------
    def tick(self, final: bool) -> None:
        for n, client in self.clients.items():
            usable = client.state.usable
            if not final and usable:
                self.carry_out(
                    self.client_eps[n], client.spend(min(usable, self.power_uj_per_tick[n]))
                )
            usable = client.state.usable
            back = usable if final else (usable // 2 if self.rng.random() < 0.03 else 0)
            back -= back % QUANTUM_UJ
            back = min(back, AMOUNT_MAX_MJ * QUANTUM_UJ)
            if back > 0 and client.can_give_back():
                self.stats[n].returns += 1
                self.carry_out(self.client_eps[n], client.give_back(back, self.now))
        if final:
            return
        for n in self.rng.sample(self.cfg.nodes, len(self.cfg.nodes)):
            usable = self.sup.state.usable
            if self.started >= self.cfg.transactions or usable < QUANTUM_UJ:
                break
            if self.sup.session(n).phase is Phase.IDLE:
                amount = min(usable, self.rng.randint(self.grant_uj // 2, self.grant_uj * 3 // 2))
                amount -= amount % QUANTUM_UJ
                self.started += 1
                self.carry_out(self.sup_ep, self.sup.begin(n, amount, self.now))

    def maybe_reset(self) -> None:
        while self.reset_points and self.reset_points[0] <= self.started:
            self.reset_points.pop(0)
            victim = self.rng.choice([0, *self.cfg.nodes])
            if victim == 0:
                self.sup_resets += 1
                self.sup.power_loss(self.now)
            else:
                self.stats[victim].resets += 1
                self.clients[victim].power_loss(self.now)

    def settled(self, final: bool) -> bool:
        returns_open = any(
            not c.can_give_back() or (final and c.state.usable >= QUANTUM_UJ)
            for c in self.clients.values()
        )
        return self.sup.is_quiescent() and self.net.in_flight() == 0 and not returns_open

    # -- main loop -----------------------------------------------------------------------
    def run(self) -> DemoResult:
        limit = int(self.cfg.duration_s * 1e6)
        next_tick, final, finished = 0, False, False
        try:
            while self.now <= limit:
                if next_tick <= self.now:
                    exhausted = self.sup.state.usable < QUANTUM_UJ and all(
                        c.can_give_back() for c in self.clients.values()
                    )
                    work_done = (
                        self.started >= self.cfg.transactions or exhausted
                    ) and self.sup.is_quiescent()
                    final = final or (work_done and self.net.in_flight() == 0)
                    self.maybe_reset()
                    self.tick(final)
                    self.observe()
                    next_tick += TICK_US
                    if final and self.settled(final):
                        finished = True
                        break
                self.step_events()
                self.now = min(
                    t for t in (next_tick, self.net.next_due(), *self.timers()) if t is not None
                )
        finally:
            self.net.close()
        return self.result(finished)

    def timers(self) -> list[int | None]:
        return [self.sup.get_timer(), *(c.get_timer() for c in self.clients.values())]

    def step_events(self) -> None:
        """Deliver every due frame and fire every due timer, observing after each."""
        while (due := self.net.next_due()) is not None and due <= self.now:
            for ep, frame in self.net.deliver_next(self.now):
                self.receive(ep, frame)
                self.observe()
        timer = self.sup.get_timer()
        if timer is not None and timer <= self.now:
            self.carry_out(self.sup_ep, self.sup.handle_timer(self.now))
            self.observe()
        for n, c in self.clients.items():
            timer = c.get_timer()
            if timer is not None and timer <= self.now:
                self.carry_out(self.client_eps[n], c.handle_timer(self.now))
                self.observe()

    def result(self, finished: bool) -> DemoResult:
        eps = [self.sup_ep, *self.client_eps.values()]
        return DemoResult(
            config=self.cfg,
            ledger=self.ledger(),
            min_dissipated=self.min_dissipated,
            first_violation_us=self.first_violation,
            nodes=self.stats,
            client_usable={n: c.state.usable for n, c in self.clients.items()},
            client_spent={n: c.state.spent for n, c in self.clients.items()},
            outcomes=self.outcomes,
            transactions_started=self.started,
            frames_sent=sum(ep.frames_sent for ep in eps),
            decode_errors=self.decode_errors,
            supervisor_resets=self.sup_resets,
            virtual_us=self.now,
            finished=finished,
            injector=self.net.injector,
        )


def run_demo(cfg: DemoConfig) -> DemoResult:
    """Run one seeded demo and return its ledger, counters and verdict."""
    return _Demo(cfg).run()
