"""Discrete-event simulation of one supervisor and K clients in virtual time.

A seeded heap of events (frame arrivals, queue samples, timer deadlines, workload) drives the
core's ``Supervisor``/``Client`` wrappers with the chosen rule set. Frames are encoded by the real
codec, pass a ``Channel`` and are decoded (corrupted ones mostly fail the CRC). After every event
the conservation ledger is evaluated. Nothing sleeps and nothing reads a clock.
"""

from __future__ import annotations

import heapq
import itertools
import random
from dataclasses import dataclass, field
from typing import Any

from canergy.codec import Codec, DecodeError
from canergy.core import Acknowledged, Action, Client, Resolved, Send, Supervisor, Timing
from canergy.core.state import Outcome, Phase
from canergy.core.variants import RUNNABLE, Variant, get_variant
from canergy.ledger import ledger
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, Direction, Message, ToClient, ToSupervisor
from canergy.sim.channel import PRESETS, Channel, ChannelModel
from canergy.sim.naive import NAIVE
from canergy.units import UJ_PER_J

STRATEGIES: dict[str, Variant] = {**RUNNABLE, **NAIVE}
SUP = 0


def strategy(name: str) -> Variant:
    return get_variant(name, STRATEGIES, "strategy")


@dataclass(frozen=True, slots=True)
class SimConfig:
    strategy: str = "hardened"
    channel: ChannelModel = field(default_factory=lambda: PRESETS["paper"])
    clients: int = 1
    duration_s: float = 60.0
    seed: int = 0
    initial: int = 10 * UJ_PER_J
    amount_min: int = 200_000
    amount_max: int = 1_000_000
    commit_ratio: float = 0.5
    return_every_s: float = 5.0
    """Mean time between a client's returns (exponential); 0: clients never return energy."""
    timeout_us: int | None = None
    """Response timeout; None: the channel model's."""
    retries: int = 1
    trace: bool = False

    def __post_init__(self) -> None:
        strategy(self.strategy)
        if not 1 <= self.clients <= 127:
            raise ValueError("clients must be 1..127")
        if self.duration_s <= 0 or self.initial < 0 or (self.timeout_us or 1) <= 0:
            raise ValueError("duration and timeout must be > 0, initial >= 0")
        if not QUANTUM_UJ <= self.amount_min <= self.amount_max:
            raise ValueError("need 1 mJ <= amount_min <= amount_max")


@dataclass(slots=True)
class SimResult:
    config: SimConfig
    transactions_started: int = 0
    committed: int = 0
    aborted: int = 0
    written_off: int = 0
    frames_sent: int = 0
    decode_errors: int = 0
    passivity_violations: int = 0
    max_generated_uj: int = 0
    final_dissipated_uj: int = 0
    worst_dissipated_uj: int = 0
    first_violation_s: float | None = None
    tx_times_us: list[int] = field(default_factory=list)
    budgets: list[tuple[float, int, int, int]] = field(default_factory=list)
    """(time s, supervisor usable µJ, clients usable µJ, dissipated µJ) after each event."""
    trace: list[dict[str, Any]] = field(default_factory=list)
    frames: list[dict[str, Any]] = field(default_factory=list)
    """Each frame sent: time, direction, type, node, arrival times ([] when lost)."""
    timeouts: list[tuple[float, int, str]] = field(default_factory=list)

    def percentile_s(self, q: float) -> float:
        if not self.tx_times_us:
            return 0.0
        times = sorted(self.tx_times_us)
        return times[min(len(times) - 1, int(q * len(times)))] / 1e6

    def summary(self) -> dict[str, Any]:
        return {
            "transactions_started": self.transactions_started,
            "committed": self.committed,
            "aborted": self.aborted,
            "written_off": self.written_off,
            "frames_sent": self.frames_sent,
            "decode_errors": self.decode_errors,
            "passivity_violations": self.passivity_violations,
            "max_generated_uj": self.max_generated_uj,
            "final_dissipated_uj": self.final_dissipated_uj,
            "worst_dissipated_uj": self.worst_dissipated_uj,
            "first_violation_s": self.first_violation_s,
            "tx_time_p50_s": round(self.percentile_s(0.5), 6),
            "tx_time_p99_s": round(self.percentile_s(0.99), 6),
        }


class Simulation:
    def __init__(self, config: SimConfig) -> None:
        self.cfg = c = config
        variant = strategy(c.strategy)
        self.timeout_us = timeout = c.timeout_us or c.channel.timeout_us
        timing = Timing(
            response_timeout_us=timeout,
            retries=c.retries,
            command_timeout_us=timeout,
            return_retry_us=timeout,
        )
        nodes = range(1, c.clients + 1)
        self.sup = Supervisor(nodes, c.initial, variant=variant, timing=timing)
        self.clients = {n: Client(n, variant=variant, timing=timing) for n in nodes}
        self.codec = Codec()
        self.channel = Channel(c.channel, c.seed)
        self.work = {n: random.Random(f"{c.seed}/work/{n}") for n in nodes}
        self.return_rng = {n: random.Random(f"{c.seed}/returns/{n}") for n in nodes}
        self.end_us = int(c.duration_s * 1e6)
        self.now = 0
        self.events: list[tuple[int, int, str, int, bytes]] = []
        self.seq = itertools.count()
        self.inbox: dict[int, list[bytes]] = {n: [] for n in (SUP, *nodes)}
        self.armed: dict[int, int | None] = {n: None for n in (SUP, *nodes)}
        self.started_at: dict[int, int] = {}
        self.result = SimResult(c)

    # -- scheduling ------------------------------------------------------------------------
    def _at(self, when: int, kind: str, where: int, data: bytes = b"") -> None:
        heapq.heappush(self.events, (when, next(self.seq), kind, where, data))

    def run(self) -> SimResult:
        sample = self.cfg.channel.sample_us
        for n in self.clients:
            self._at(0, "start", n)
            if sample:  # queues are sampled periodically, at a random phase per node
                self._at(self.work[n].randrange(sample), "tick", n)
            self._next_return(n)
        if sample:
            self._at(random.Random(f"{self.cfg.seed}/phase").randrange(sample), "tick", SUP)
        while self.events and self.events[0][0] <= self.end_us:
            self.now, _, kind, where, data = heapq.heappop(self.events)
            getattr(self, f"_on_{kind}")(where, data)
            self._observe(kind, where)
        self.result.final_dissipated_uj = self._ledger().dissipated
        return self.result

    # -- events ----------------------------------------------------------------------------
    def _on_arrive(self, where: int, data: bytes) -> None:
        if self.cfg.channel.sample_us:
            self.inbox[where].append(data)
        else:
            self._deliver(where, data)

    def _on_tick(self, where: int, data: bytes) -> None:
        """A sampled node handles its queue, then whatever timed out by now (as a chart that
        runs once per sample does)."""
        frames, self.inbox[where] = self.inbox[where], []
        for frame in frames:
            self._deliver(where, frame)
        owner = self.sup if where == SUP else self.clients[where]
        deadline = owner.get_timer()
        if deadline is not None and deadline <= self.now:
            self._on_timer(where, b"")
        self._at(self.now + self.cfg.channel.sample_us, "tick", where)

    def _on_timer(self, where: int, data: bytes) -> None:
        self.armed[where] = None
        if where == SUP:
            actions = self.sup.handle_timer(self.now)
        else:
            actions = self.clients[where].handle_timer(self.now)
        if any(isinstance(a, Send) for a in actions):
            self.result.timeouts.append(
                (self.now / 1e6, where, "supervisor" if where == SUP else "client")
            )
        self._carry_out(where, actions)

    def _on_start(self, node: int, data: bytes) -> None:
        if self.sup.session(node).phase is not Phase.IDLE:
            return
        rng = self.work[node]
        amount = rng.randrange(self.cfg.amount_min, self.cfg.amount_max + 1, QUANTUM_UJ)
        amount = min(amount, self.sup.state.usable - self.sup.state.usable % QUANTUM_UJ)
        if amount < QUANTUM_UJ:
            self._at(self.now + self.timeout_us, "start", node)  # wait for returns
            return
        self.result.transactions_started += 1
        self.started_at[node] = self.now
        self._carry_out(SUP, self.sup.begin(node, amount, self.now))

    def _on_give_back(self, node: int, data: bytes) -> None:
        client = self.clients[node]
        usable = client.state.usable
        fraction = self.return_rng[node].uniform(0.2, 0.8)
        amount = int(usable * fraction) // QUANTUM_UJ * QUANTUM_UJ
        if amount >= QUANTUM_UJ and client.can_give_back():
            self._carry_out(
                node, client.give_back(min(amount, AMOUNT_MAX_MJ * QUANTUM_UJ), self.now)
            )
        self._next_return(node)

    # -- plumbing --------------------------------------------------------------------------
    def _next_return(self, node: int) -> None:
        mean = self.cfg.return_every_s
        if mean > 0:
            gap = int(self.return_rng[node].expovariate(1 / mean) * 1e6) + 1
            self._at(self.now + gap, "give_back", node)

    def _deliver(self, where: int, data: bytes) -> None:
        to_client = where != SUP
        direction = Direction.TO_CLIENT if to_client else Direction.TO_SUPERVISOR
        arbitration_id, payload = data[:4], data[4:]
        try:
            msg = self.codec.decode(
                int.from_bytes(arbitration_id, "little"), payload, direction=direction
            )
        except DecodeError:
            self.result.decode_errors += 1
            self._row("drop", where, None, "decode error")
            return
        self._row("receive", where, msg)
        if to_client:
            assert isinstance(msg, ToClient)
            self._carry_out(where, self.clients[where].receive(msg, self.now))
        elif isinstance(msg, ToSupervisor):
            self._carry_out(SUP, self.sup.receive(msg, self.now))

    def _carry_out(self, where: int, actions: list[Action]) -> None:
        for action in actions:
            if isinstance(action, Send):
                self._send(action.message)
            elif isinstance(action, Acknowledged):
                commit = self.work[action.node].random() < self.cfg.commit_ratio
                decide = self.sup.commit if commit else self.sup.abort
                self._carry_out(SUP, decide(action.node, self.now))
            elif isinstance(action, Resolved):
                self._resolved(action)
        self._arm(where)

    def _resolved(self, action: Resolved) -> None:
        r = self.result
        if action.outcome is Outcome.COMMITTED:
            r.committed += 1
        elif action.outcome is Outcome.ABORTED:
            r.aborted += 1
        else:
            r.written_off += 1
        started = self.started_at.pop(action.node, None)
        if started is not None:
            r.tx_times_us.append(self.now - started)
        self._at(self.now, "start", action.node)  # the next transaction follows at once

    def _arm(self, where: int) -> None:
        if self.cfg.channel.sample_us:
            return  # sampled nodes look at their timers on each tick
        owner = self.sup if where == SUP else self.clients[where]
        deadline = owner.get_timer()
        if deadline is not None and deadline != self.armed[where]:
            self.armed[where] = deadline
            self._at(max(deadline, self.now), "timer", where)

    def _send(self, msg: Message) -> None:
        to_client = msg.TYPE.direction is Direction.TO_CLIENT
        arbitration_id, data = self.codec.encode(msg)
        self.result.frames_sent += 1
        fates = self.channel.link(msg.node, to_client).fate(data)
        where = msg.node if to_client else SUP
        for delay, payload in fates:
            self._at(
                self.now + delay, "arrive", where, arbitration_id.to_bytes(4, "little") + payload
            )
        if self.cfg.trace:
            self.result.frames.append(
                {
                    "t": self.now / 1e6,
                    "to_client": to_client,
                    "node": msg.node,
                    "type": msg.TYPE.name,
                    "arrivals": [(self.now + d) / 1e6 for d, _ in fates],
                }
            )
        self._row("send" if fates else "send-lost", where, msg)

    def _ledger(self) -> Any:
        return ledger(self.sup.state, [c.state for c in self.clients.values()])

    def _observe(self, kind: str, where: int) -> None:
        books = self._ledger()
        r = self.result
        d = books.dissipated
        if d < 0:
            r.passivity_violations += 1
            r.max_generated_uj = max(r.max_generated_uj, -d)
            if r.first_violation_s is None:
                r.first_violation_s = self.now / 1e6
        r.worst_dissipated_uj = max(r.worst_dissipated_uj, d)
        if self.cfg.trace:
            point = (self.now / 1e6, books.supervisor_usable, books.clients_usable, d)
            if not r.budgets or r.budgets[-1][1:] != point[1:]:
                r.budgets.append(point)
                self._row("ledger", where, None, f"after {kind}")

    def _row(self, event: str, where: int, msg: Message | None, detail: str = "") -> None:
        if not self.cfg.trace:
            return
        sup_usable = self.sup.state.usable
        clients = sum(c.state.usable for c in self.clients.values())
        self.result.trace.append(
            {
                "time_s": f"{self.now / 1e6:.6f}",
                "strategy": self.cfg.strategy,
                "event": event,
                "at": "supervisor" if where == SUP else f"node {where}",
                "message": "" if msg is None else msg.TYPE.name,
                "fields": "" if msg is None else _fields(msg),
                "detail": detail,
                "supervisor_usable_uj": sup_usable,
                "clients_usable_uj": clients,
                "sum_uj": sup_usable + clients,
                "dissipated_uj": self._ledger().dissipated,
            }
        )


def _fields(msg: Message) -> str:
    return " ".join(f"{k}={getattr(msg, k)}" for k in msg.__slots__ if k != "node")


def simulate(config: SimConfig) -> SimResult:
    return Simulation(config).run()
