"""``canergy demo --topology tree``: a root supervisor, gateways on their own buses, nodes below.

Virtual time, one seeded event queue. Every frame goes through the codec (CRC included) and a
``FaultInjector`` of its bus: the root's bus joins the root and its gateways, each gateway has a
bus of its own for its nodes. Gateways run ``canergy.core.gateway.Gateway`` (the live gateway's
core); the root and the gateways top up from TELEMETRY like ``canergy supervisor --target``,
gateways return what they hold above ``gateway_return_above``, nodes spend and return. Power
losses strike gateways, nodes and the root: each restarts from its persistent record (what the
gateway's one state file holds; the live gateway's file is tested on its own).

A *work* phase grants for ``duration_us``; then a *drain* phase grants nothing, nodes return all
they hold and gateways return everything upstream, until the tree is quiet. The tree's ledger
(every level and every gateway's link) is checked after every event (``observe_every=1``) or
every that many events; with 0, only at the end (the scale bench).
"""

from __future__ import annotations

import heapq
import itertools
import random
import resource
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

from canergy.codec import Codec, DecodeError
from canergy.core import Acknowledged, Action, Client, Resolved, Send, Supervisor, Timing
from canergy.core.gateway import Gateway, link_gap
from canergy.core.state import Outcome, Phase
from canergy.faults import FaultInjector, FaultProfile
from canergy.ledger import TreeLedger, ledger
from canergy.messages import (
    AMOUNT_MAX_MJ,
    QUANTUM_UJ,
    Message,
    Telemetry,
    ToClient,
    ToSupervisor,
)
from canergy.units import UJ_PER_J, US_PER_S

TICK_US = 10_000
TELEMETRY_US = 100_000
LARGEST = AMOUNT_MAX_MJ * QUANTUM_UJ
ROOT = 0
"""Bus 0 is the root's; bus g (1..gateways) is gateway g's."""


@dataclass(frozen=True, slots=True)
class TreeConfig:
    gateways: int = 2
    nodes: int = 3
    """Nodes under each gateway (ids 1..nodes on its bus)."""
    initial: int = 30 * UJ_PER_J
    duration_us: int = 60 * US_PER_S
    """Virtual time of the work phase; the drain phase may take as long again."""
    faults: FaultProfile = field(
        default_factory=lambda: FaultProfile(loss=0.1, duplicate=0.05, reorder=0.05, corrupt=0.01)
    )
    seed: int = 0
    gateway_resets: int = 2
    node_resets: int = 2
    root_resets: int = 1
    gateway_target: int = 4 * UJ_PER_J
    gateway_return_above: int = 8 * UJ_PER_J
    node_target: int = 500_000
    node_power_uw: tuple[int, int] = (20_000, 120_000)
    commit_ratio: float = 0.9
    observe_every: int = 1
    timing: Timing = field(default_factory=lambda: Timing(20_000, 3, 40_000, 40_000))

    def __post_init__(self) -> None:
        if not 1 <= self.gateways <= 127 or not 1 <= self.nodes <= 127:
            raise ValueError("1-127 gateways, 1-127 nodes per gateway")
        if self.gateway_return_above < self.gateway_target:
            raise ValueError("gateways would return what the root tops them up with")


@dataclass(slots=True)
class LevelStats:
    committed: int = 0
    aborted: int = 0
    written_off: int = 0
    begun: int = 0


@dataclass(slots=True)
class TreeResult:
    config: TreeConfig
    ledger: TreeLedger
    min_dissipated: int
    first_violation_us: int | None
    stats: dict[str, LevelStats]
    frames_sent: int
    frames_lost: int
    decode_errors: int
    resets: dict[str, int]
    virtual_us: int
    finished: bool
    events: int
    cpu_s: float
    wall_s: float
    max_rss_kib: int
    spent_uj: int

    @property
    def passive(self) -> bool:
        return self.ledger.passive and self.first_violation_us is None

    @property
    def transactions(self) -> int:
        return sum(s.committed + s.aborted + s.written_off for s in self.stats.values())

    def as_json(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "topology": "tree",
            "gateways": cfg.gateways,
            "nodes_per_gateway": cfg.nodes,
            "seed": cfg.seed,
            "passive": self.passive,
            "finished": self.finished,
            "ledger": self.ledger.as_json(),
            "min_dissipated_uj": self.min_dissipated,
            "first_violation_us": self.first_violation_us,
            "levels": {k: asdict(v) for k, v in self.stats.items()},
            "transactions": self.transactions,
            "frames_sent": self.frames_sent,
            "frames_lost": self.frames_lost,
            "decode_errors": self.decode_errors,
            "resets": self.resets,
            "spent_uj": self.spent_uj,
            "virtual_s": round(self.virtual_us / US_PER_S, 3),
            "events": self.events,
            "cpu_s": round(self.cpu_s, 3),
            "wall_s": round(self.wall_s, 3),
            "max_rss_kib": self.max_rss_kib,
        }


@dataclass(slots=True)
class _Seen:
    """What a supervisor knows of one client from its TELEMETRY."""

    level: int | None = None
    level_at: int = -1
    ended_at: int = 0


def level_name(bus: int) -> str:
    """``root`` for bus 0, ``gateway g`` for gateway g's bus."""
    return "root" if bus == ROOT else f"gateway {bus}"


Key = tuple[int, int]
"""(bus, node): node 0 is the bus's supervisor."""


class TreeRun:
    def __init__(self, cfg: TreeConfig, gateway_class: type[Gateway] = Gateway) -> None:
        """``gateway_class``: tests put a gateway with broken rules here."""
        self.cfg = cfg
        self.rng = random.Random(f"tree-{cfg.seed}")
        self.codec = Codec()
        self.now = 0
        t = cfg.timing
        gws = range(1, cfg.gateways + 1)
        self.root = Supervisor(gws, cfg.initial, timing=t)
        self.gateways = {
            g: gateway_class(g, range(1, cfg.nodes + 1), up_timing=t, down_timing=t) for g in gws
        }
        self.nodes = {(g, n): Client(n, timing=t) for g in gws for n in range(1, cfg.nodes + 1)}
        lo, hi = cfg.node_power_uw
        self.power = {k: self.rng.randint(lo, hi) for k in self.nodes}
        self.seen: dict[Key, _Seen] = {(0, g): _Seen() for g in gws}
        self.seen.update({k: _Seen() for k in self.nodes})
        self.injectors = [
            FaultInjector(cfg.faults, random.Random(f"tree-{cfg.seed}-bus-{b}"))
            for b in range(cfg.gateways + 1)
        ]
        self.events: list[tuple[int, int, int, int, int, bytes]] = []
        self.seq = itertools.count()
        self.armed: dict[Key, int] = {}
        self.stats = {level_name(b): LevelStats() for b in range(cfg.gateways + 1)}
        self.frames_sent = 0
        self.decode_errors = 0
        self.count_events = 0
        self.draining = False
        self.min_dissipated = cfg.initial
        self.first_violation: int | None = None
        self.resets = {"root": 0, "gateways": 0, "nodes": 0}
        span = max(cfg.duration_us, 1)
        draws = [
            ("root", cfg.root_resets),
            ("gateways", cfg.gateway_resets),
            ("nodes", cfg.node_resets),
        ]
        self.reset_plan = sorted(
            (self.rng.randrange(span), who) for who, k in draws for _ in range(k)
        )
        self.next_telemetry = 0

    # -- the ledger ----------------------------------------------------------------------------
    def tree_ledger(self) -> TreeLedger:
        levels = {"root": ledger(self.root.state, [g.up.state for g in self.gateways.values()])}
        for g, gw in self.gateways.items():
            clients = [self.nodes[(g, n)].state for n in range(1, self.cfg.nodes + 1)]
            levels[level_name(g)] = ledger(gw.down.state, clients)
        gaps = {
            level_name(g): link_gap(gw.up.state, gw.down.state) for g, gw in self.gateways.items()
        }
        return TreeLedger(levels, gaps)

    def observe(self) -> None:
        tree = self.tree_ledger()
        worst = min(
            [led.dissipated for led in tree.levels.values()] + [-max(tree.link_gaps.values())]
        )
        self.min_dissipated = min(self.min_dissipated, worst)
        if not tree.passive and self.first_violation is None:
            self.first_violation = self.now

    # -- frames --------------------------------------------------------------------------------
    def send(self, bus: int, msg: Message) -> None:
        ident, data = self.codec.encode(msg)
        self.frames_sent += 1
        for delay, copy in self.injectors[bus].fate(data):
            heapq.heappush(self.events, (self.now + delay, next(self.seq), 0, bus, ident, copy))

    def deliver(self, bus: int, ident: int, data: bytes) -> None:
        try:
            msg = self.codec.decode(ident, data)
        except DecodeError:
            self.decode_errors += 1
            return
        if isinstance(msg, Telemetry):
            seen = self.seen[(bus, msg.node)]
            seen.level, seen.level_at = msg.level_mj * QUANTUM_UJ, self.now
        elif isinstance(msg, ToClient) and bus == ROOT:
            self.carry_out(
                (ROOT, msg.node), self.gateways[msg.node].receive_upstream(msg, self.now)
            )
        elif isinstance(msg, ToClient):
            self.carry_out((bus, msg.node), self.nodes[(bus, msg.node)].receive(msg, self.now))
        elif isinstance(msg, ToSupervisor) and bus == ROOT:
            self.carry_out((ROOT, 0), self.root.receive(msg, self.now))
        elif isinstance(msg, ToSupervisor):
            self.carry_out((bus, 0), self.gateways[bus].down.receive(msg, self.now))

    def carry_out(self, who: Key, actions: Iterable[Action]) -> None:
        """Actions of the supervisor (node 0) or the client ``who`` on bus ``who[0]``."""
        bus = who[0]
        for a in actions:
            if isinstance(a, Send):
                self.send(bus, a.message)
            elif isinstance(a, Acknowledged):
                sup = self.supervisor(bus)
                decide = sup.commit if self.rng.random() < self.cfg.commit_ratio else sup.abort
                self.carry_out(who, decide(a.node, self.now))
            elif isinstance(a, Resolved):
                self.resolved(bus, a)
        self.arm(who)

    def resolved(self, bus: int, a: Resolved) -> None:
        stats = self.stats[level_name(bus)]
        if a.outcome is Outcome.COMMITTED:
            stats.committed += 1
        elif a.outcome is Outcome.ABORTED:
            stats.aborted += 1
        else:
            stats.written_off += 1
        self.seen[(bus, a.node)].ended_at = self.now

    def supervisor(self, bus: int) -> Supervisor:
        if bus == ROOT:
            return self.root
        down = self.gateways[bus].down
        assert isinstance(down, Supervisor)  # the demo's gateways run the Python core
        return down

    # -- timers: one event per armed deadline ----------------------------------------------------
    def timer_of(self, who: Key) -> int | None:
        bus, node = who
        if node == 0:
            return self.supervisor(bus).get_timer()
        if bus == ROOT:
            return self.gateways[node].up.get_timer()
        return self.nodes[who].get_timer()

    def arm(self, who: Key) -> None:
        due = self.timer_of(who)
        if due is not None and self.armed.get(who) != due:
            self.armed[who] = due
            heapq.heappush(
                self.events, (max(due, self.now), next(self.seq), 1, who[0], who[1], b"")
            )

    def fire(self, who: Key) -> None:
        due = self.timer_of(who)
        if due is None or due > self.now:
            return
        self.armed.pop(who, None)
        bus, node = who
        if node == 0:
            actions = self.supervisor(bus).handle_timer(self.now)
        elif bus == ROOT:
            actions = self.gateways[node].handle_upstream_timer(self.now)
        else:
            actions = self.nodes[who].handle_timer(self.now)
        self.carry_out(who, actions)

    # -- workload ------------------------------------------------------------------------------
    def tick(self) -> None:
        while self.reset_plan and self.reset_plan[0][0] <= self.now:
            self.reset(self.reset_plan.pop(0)[1])
        telemetry = self.now >= self.next_telemetry
        if telemetry:
            self.next_telemetry = self.now + TELEMETRY_US
        for key, client in self.nodes.items():
            self.node_tick(key, client, telemetry)
        for g, gw in self.gateways.items():
            self.gateway_tick(g, gw, telemetry)
        if not self.draining:
            self.top_up(ROOT, self.cfg.gateway_target)
            for g in self.gateways:
                self.top_up(g, self.cfg.node_target)

    def node_tick(self, key: Key, client: Client, telemetry: bool) -> None:
        usable = client.state.usable
        need = self.power[key] * TICK_US // US_PER_S
        if usable and need and not self.draining:
            self.carry_out(key, client.spend(min(usable, need), self.now))
        usable = client.state.usable
        keep = 0 if self.draining else 2 * self.cfg.node_target
        excess = usable - keep - (usable - keep) % QUANTUM_UJ
        if excess > 0 and client.can_give_back():
            self.carry_out(key, client.give_back(min(excess, LARGEST), self.now))
        if telemetry:
            self.send(key[0], Telemetry(key[1], client.state.usable // QUANTUM_UJ))

    def gateway_tick(self, g: int, gw: Gateway, telemetry: bool) -> None:
        keep = 0 if self.draining else self.cfg.gateway_return_above
        usable = gw.down.state.usable
        excess = usable - keep - (usable - keep) % QUANTUM_UJ
        if excess > 0 and gw.can_give_back():
            self.carry_out((ROOT, g), gw.give_back(min(excess, LARGEST), self.now))
        if telemetry:
            self.send(ROOT, Telemetry(g, gw.down.state.usable // QUANTUM_UJ))

    def top_up(self, bus: int, target: int) -> None:
        sup = self.supervisor(bus)
        for s in sup.state.sessions:
            seen = self.seen[(bus, s.node)]
            if s.phase is not Phase.IDLE or seen.level is None or seen.level_at <= seen.ended_at:
                continue
            want = min(target - seen.level, sup.state.usable, LARGEST)
            want -= want % QUANTUM_UJ
            if want > 0:
                self.stats[level_name(bus)].begun += 1
                self.carry_out((bus, 0), sup.begin(s.node, want, self.now))

    def reset(self, who: str) -> None:
        """A power loss: volatile state gone, restart from the persistent record."""
        self.resets[who] += 1
        if who == "root":
            self.root.power_loss(self.now)
            self.arm((ROOT, 0))
        elif who == "gateways":
            g = self.rng.randrange(1, self.cfg.gateways + 1)
            self.gateways[g].power_loss(self.now)
            self.arm((ROOT, g))
            self.arm((g, 0))
        else:
            key = self.rng.choice(sorted(self.nodes))
            self.nodes[key].power_loss(self.now)
            self.arm(key)

    # -- main loop -----------------------------------------------------------------------------
    def quiet(self) -> bool:
        """Nothing open, nothing pending, nothing left below the root that a return could carry
        (a return carries whole mJ: a node may keep less than 1 mJ)."""
        sups = [self.root, *(gw.down for gw in self.gateways.values())]
        clients = [c.state for c in self.nodes.values()] + [
            gw.up.state for gw in self.gateways.values()
        ]
        return (
            all(s.is_quiescent() for s in sups)
            and all(c.usable < QUANTUM_UJ and c.return_pending == 0 for c in clients)
            and all(gw.down.state.usable == 0 for gw in self.gateways.values())
        )

    def run(self) -> TreeResult:
        start_cpu, start_wall = time.process_time(), time.perf_counter()
        limit = 2 * self.cfg.duration_us
        next_tick = 0
        finished = False
        while self.now <= limit:
            if self.now >= next_tick:
                self.draining = self.now >= self.cfg.duration_us
                self.tick()
                next_tick += TICK_US
                if self.cfg.observe_every:
                    self.observe()
                if self.draining and self.quiet():
                    finished = True
                    break
            while self.events and self.events[0][0] <= next_tick:
                when, _, kind, a, b, data = heapq.heappop(self.events)
                self.now = max(self.now, when)
                if kind == 0:
                    self.deliver(a, b, data)
                else:
                    self.fire((a, b))
                self.count_events += 1
                if self.cfg.observe_every and self.count_events % self.cfg.observe_every == 0:
                    self.observe()
            self.now = next_tick
        self.observe()
        return TreeResult(
            config=self.cfg,
            ledger=self.tree_ledger(),
            min_dissipated=self.min_dissipated,
            first_violation_us=self.first_violation,
            stats=self.stats,
            frames_sent=self.frames_sent,
            frames_lost=sum(i.counters.lost for i in self.injectors),
            decode_errors=self.decode_errors,
            resets=self.resets,
            virtual_us=self.now,
            finished=finished,
            events=self.count_events,
            cpu_s=time.process_time() - start_cpu,
            wall_s=time.perf_counter() - start_wall,
            max_rss_kib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
            spent_uj=sum(c.state.spent for c in self.nodes.values()),
        )


def run_tree(cfg: TreeConfig) -> TreeResult:
    return TreeRun(cfg).run()


def format_tree(r: TreeResult) -> str:
    cfg = r.config
    led = r.ledger
    lines = [
        f"tree: root -> {cfg.gateways} gateway(s) -> {cfg.nodes} node(s) each, seed {cfg.seed}, "
        f"faults on every bus (loss {cfg.faults.loss:g}, duplicate {cfg.faults.duplicate:g}, "
        f"reorder {cfg.faults.reorder:g}, corrupt {cfg.faults.corrupt:g})",
        f"power losses: root {r.resets['root']}, gateways {r.resets['gateways']}, "
        f"nodes {r.resets['nodes']}; {r.frames_sent:,} frames sent, {r.frames_lost:,} lost, "
        f"{r.decode_errors:,} refused by the codec (CRC); {r.virtual_us / US_PER_S:.1f} s virtual",
        "",
        f"{'level':<12}{'committed':>10}{'aborted':>9}{'written off':>13}"
        f"{'held (J)':>11}{'dissipated (J)':>16}",
    ]
    for name, level in led.levels.items():
        s = r.stats[name]
        lines.append(
            f"{name:<12}{s.committed:>10}{s.aborted:>9}{s.written_off:>13}"
            f"{level.held / UJ_PER_J:>11.3f}{level.dissipated / UJ_PER_J:>16.3f}"
        )
    gaps = ", ".join(f"{k} {v:+d} µJ" for k, v in led.link_gaps.items())
    lines += [
        "",
        f"gateway links (energy created between a gateway's two roles): {gaps}",
        f"tree: initial {cfg.initial / UJ_PER_J:.3f} J; spent by the actuators "
        f"{r.spent_uj / UJ_PER_J:.3f} J, back at the root "
        f"{led.levels['root'].supervisor_usable / UJ_PER_J:.3f} J, dissipated "
        f"{led.dissipated / UJ_PER_J:.3f} J, the rest still held below",
        f"lowest dissipation seen at any level: {r.min_dissipated / UJ_PER_J:.3f} J "
        f"({'never negative' if r.first_violation_us is None else 'NEGATIVE'})",
        ("PASSIVE: nothing created at any level" if r.passive else "VIOLATION: energy created")
        + ("" if r.finished else " (the drain did not finish in time)"),
    ]
    return "\n".join(lines)
