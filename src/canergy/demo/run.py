"""The ``canergy demo`` run: a supervisor and several clients on a virtual bus, under faults.

Runs in virtual time (no sleeping), so a seed reproduces the run exactly. A run has two phases:
*work* (actuators spend, clients now and then return energy, the supervisor begins transactions)
until no transaction will begin any more and every begun one has ended, then *drain* (clients
return everything they hold) until the network has settled. Both stop at the duration limit.
The observer checks the conservation ledger after every event and remembers the lowest
dissipation seen.
"""

from __future__ import annotations

import itertools
import random
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack

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
)
from canergy.core.state import Outcome, Phase
from canergy.demo.capture import Capture
from canergy.demo.config import MAX_AMOUNT_UJ, DemoConfig
from canergy.demo.result import DemoResult, NodeStats
from canergy.demo.virtual_net import Endpoint, VirtualNetwork
from canergy.faults import FaultInjector
from canergy.ledger import Ledger, ledger
from canergy.messages import QUANTUM_UJ, Direction, ToClient, ToSupervisor

TICK_US = 10_000


class DemoRun:
    """One run: the nodes, the network, the workload and the observer."""

    def __init__(self, cfg: DemoConfig, net: VirtualNetwork) -> None:
        self.cfg = cfg
        self.rng = random.Random(cfg.seed)
        self.net = net
        self.sup = Supervisor(cfg.nodes, cfg.initial, variant=cfg.variant, timing=cfg.timing)
        self.sup_ep = net.endpoint("supervisor", net.codec.supervisor_filters())
        self.clients = {n: Client(n, variant=cfg.variant, timing=cfg.timing) for n in cfg.nodes}
        self.client_eps = {
            n: net.endpoint(f"node {n}", net.codec.client_filters(n)) for n in cfg.nodes
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
            msg = self.net.codec.decode(
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
    def work_tick(self) -> None:
        """Actuators spend, clients now and then return half their budget, grants begin."""
        for n, client in self.clients.items():
            if client.state.usable:
                spend = min(client.state.usable, self.power_uj_per_tick[n])
                self.carry_out(self.client_eps[n], client.spend(spend, self.now))
            self.give_back(n, client.state.usable // 2 if self.rng.random() < 0.03 else 0)
        self.begin_transactions()

    def drain_tick(self) -> None:
        """Every client returns what it holds; nothing is spent and nothing begins."""
        for n, client in self.clients.items():
            self.give_back(n, client.state.usable)

    def give_back(self, n: int, amount: int) -> None:
        """Node ``n`` returns ``amount`` in whole mJ, at most one frame's worth, if it may."""
        amount = min(amount - amount % QUANTUM_UJ, MAX_AMOUNT_UJ)
        if amount > 0 and self.clients[n].can_give_back():
            self.stats[n].returns += 1
            self.carry_out(self.client_eps[n], self.clients[n].give_back(amount, self.now))

    def begin_transactions(self) -> None:
        """Offer idle nodes, in random order, a grant while transactions and budget remain."""
        for n in self.rng.sample(self.cfg.nodes, len(self.cfg.nodes)):
            usable = self.sup.state.usable
            if self.all_started() or usable < QUANTUM_UJ:
                break
            if self.sup.session(n).phase is Phase.IDLE:
                amount = min(usable, self.rng.randint(*self.cfg.grant_range_uj))
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

    # -- conditions ----------------------------------------------------------------------
    def all_started(self) -> bool:
        return self.started >= self.cfg.transactions

    def returns_pending(self) -> bool:
        """Some client's return still waits for its acknowledgement."""
        return not all(c.can_give_back() for c in self.clients.values())

    def budget_exhausted(self) -> bool:
        """The supervisor cannot grant a whole mJ and no pending return will refill it."""
        return self.sup.state.usable < QUANTUM_UJ and not self.returns_pending()

    def clients_hold_energy(self) -> bool:
        """Some client holds at least a whole mJ it could return."""
        return any(c.state.usable >= QUANTUM_UJ for c in self.clients.values())

    def quiet(self) -> bool:
        """No transaction is open at the supervisor and no frame is in flight."""
        return self.sup.is_quiescent() and self.net.in_flight() == 0

    def work_done(self) -> bool:
        """No transaction will begin any more and every begun one has ended."""
        return (self.all_started() or self.budget_exhausted()) and self.quiet()

    def settled(self) -> bool:
        """Quiet, no return pending and nothing left for a client to return."""
        return self.quiet() and not self.returns_pending() and not self.clients_hold_energy()

    # -- main loop -----------------------------------------------------------------------
    def run(self) -> DemoResult:
        """Work, then drain, sharing one clock that stops at the duration limit."""
        ticks = self.ticks(self.cfg.duration_us)
        finished = self.work(ticks) and self.drain(ticks)
        return self.result(finished)

    def ticks(self, limit: int) -> Iterator[int]:
        """Yield the time of every tick up to ``limit``; frames and timers due in between are
        handled when the caller asks for the next tick."""
        next_tick = 0
        while self.now <= limit:
            if next_tick <= self.now:
                yield self.now
                next_tick += TICK_US
            self.step_events()
            self.now = min(
                t for t in (next_tick, self.net.next_due(), *self.timers()) if t is not None
            )

    def tick(self, workload: Callable[[], None]) -> None:
        """Power losses now due, this phase's workload, then the observer."""
        self.maybe_reset()
        workload()
        self.observe()

    def work(self, ticks: Iterator[int]) -> bool:
        """Work ticks until the work is done (``True``, leaving that tick to ``drain``)."""
        for _ in ticks:
            if self.work_done():
                return True
            self.tick(self.work_tick)
        return False

    def drain(self, ticks: Iterator[int]) -> bool:
        """Drain ticks, from the one ``work`` left on, until the network settled (``True``)."""
        for _ in itertools.chain([self.now], ticks):
            self.tick(self.drain_tick)
            if self.settled():
                return True
        return False

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
    """Run one seeded demo and return its ledger, counters and verdict.

    The capture (``cfg.log``) is opened before any bus, and every bus is shut down on every path.
    """
    injector = FaultInjector(cfg.faults, random.Random(f"faults-{cfg.seed}"))
    with ExitStack() as stack:
        capture = stack.enter_context(Capture(cfg.log)) if cfg.log is not None else None
        on_frame = None if capture is None else capture.write
        net = VirtualNetwork(Codec(), injector, on_frame=on_frame, epoch=time.time())
        return DemoRun(cfg, stack.enter_context(net)).run()
