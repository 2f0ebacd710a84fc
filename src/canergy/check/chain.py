"""The chain root → gateway → node(s): every interleaving within bounds, through the same core.

The root is a supervisor of one node, the gateway (``canergy.core.gateway.Gateway``); the gateway
supervises ``clients`` nodes on its own bus. Both legs lose, duplicate and reorder frames (a leg's
frames in flight are a multiset); root, gateway and nodes lose power (the gateway's two roles
restart from their one record). Time is abstract, as in ``model``. After every step the tree's
ledger is checked: no level, and no gateway between its roles, may create energy.

Two gateway rules can be broken on purpose, each yielding a counterexample: ``early-grant``
grants downstream what the upstream intention holds before the upstream commit;
``split-save`` keeps the two roles in two files written one after the other, and a power loss
between the two writes (``gateway_torn_write``) restarts the upstream role from its older record.

``old_copies``: the gateway restarts from its record as it was before its last write (a backup
or a VM snapshot put back, assumption 2 dropped for the gateway): under the hardened rules that
creates energy, under the witnessed ones (every start a RESUME the root confirms, forwarding a
numbered DRAW the root acknowledges first) it must not. The ledger keeps what the copy forgets,
as for a node's old copy (``model.restored_ghost``): the largest Rc and the spent the root saw
from the gateway's upstream role, and what entered and left the level below after the copy was
written (it did enter and leave, whatever the copy says). Every start draws a nonce no earlier
one drew (``model.RESTART_NONCE``...).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

from canergy.check.model import (
    OLD_COPY_NONCE,
    RESTART_NONCE,
    SUPERVISOR_NONCE,
    UNIT,
    WINDOW,
    Flight,
    message_key,
    restored_ghost,
)
from canergy.check.search import breadth_first
from canergy.core.actions import Action, Send
from canergy.core.errors import LocalProtocolError
from canergy.core.gateway import (
    STARTING,
    Below,
    Gateway,
    GatewayState,
    forward,
    link_gap,
    may_give_back,
)
from canergy.core.inputs import (
    COMMAND_TIMEOUT,
    POWER_LOSS,
    RESPONSE_TIMEOUT,
    RETURN_TIMEOUT,
    Begin,
    Decide,
    GiveBack,
    PowerLoss,
    Spend,
)
from canergy.core.state import ClientState, Decision, Phase, Session, SupervisorState
from canergy.core.supervisor import apply_session, inject_into, unconfirmed
from canergy.core.table import Event
from canergy.core.timing import Timing
from canergy.core.variants import Variant, get_variant
from canergy.frozen import evolve
from canergy.ledger import NOT_LOST, LostRecord, TreeLedger, ledger
from canergy.messages import Direction, Message, ToClient, ToSupervisor

GATEWAY_NODE = 1
BROKEN_RULES = ("early-grant", "split-save")


@dataclass(frozen=True, slots=True)
class ChainBounds:
    """What the exploration may spend. Energies in units (1 unit = 1 mJ)."""

    clients: int = 1
    transactions: int = 2
    """Transactions each supervisor (root, gateway) may begin."""
    losses: int = 1
    duplicates: int = 1
    power_losses: int = 1
    """Power losses of root, gateway and nodes, in all."""
    in_flight: int = 2
    """Frames in flight on each leg."""
    units: int = 1
    retries: int = 1
    old_copies: int = 0
    """Restarts of the gateway from its record before its last write."""

    def timing(self) -> Timing:
        return Timing(
            response_timeout_us=0,
            retries=self.retries,
            command_timeout_us=0,
            return_retry_us=0,
            window=WINDOW,
        )


@dataclass(frozen=True, slots=True)
class ChainWorld:
    root: SupervisorState
    gateway: GatewayState
    nodes: tuple[ClientState, ...]
    up: Flight = frozenset()
    down: Flight = frozenset()
    root_started: int = 0
    gateway_started: int = 0
    lost: int = 0
    duplicated: int = 0
    power_lost: int = 0
    advanced: int = 0
    """``early-grant`` only: energy granted downstream ahead of an upstream commit."""
    torn: ClientState | None = None
    """``split-save`` only: the upstream record before the latest step that changed both roles'
    records; the downstream file was written first, so a crash in between restarts from it."""
    older: GatewayState | None = None
    """With ``old_copies``: the gateway's record before its last write."""
    old_copied: int = 0
    ghost_up: LostRecord = NOT_LOST
    """What the root saw of the gateway's upstream role that restored copies forgot."""
    ghost_in: int = 0
    ghost_out: int = 0
    """Injected into and withdrawn from the level below after the restored copies were
    written."""
    dropped: int = 0
    """Us below a start found behind dropped (``Gateway.dropped``): the record's withdrawal
    and its spent above both go down by it, but nothing left the level; the ledger counts it
    as lost there (a copy's Us whose energy had already left counts then as nothing)."""

    def passive(self) -> bool:
        """Every level and the gateway between its roles passive; after a restored copy, the
        tree as a whole: where the energy the copy forgot went (a RETURN it voided still
        holds it, a withdrawal it undid did not) no observer of the records can tell level by
        level, but the ghost terms cancel in the tree's sum, which is what the supplies hold
        against what the root started with."""
        tree = self.ledger()
        return tree.passive if not self.old_copied else tree.dissipated >= 0

    def ledger(self) -> TreeLedger:
        gw = self.gateway
        ghost_spent = self.ghost_up.spent
        below = ledger(gw.down, self.nodes)
        below = replace(
            below,
            injected=below.injected + self.ghost_in,
            withdrawn=below.withdrawn + self.ghost_out - self.dropped,
        )
        if gw.up.phase in STARTING:  # Us below counts once the supervisor above confirms it
            below = replace(below, supervisor_usable=min(gw.down.usable, 0))
        up = self.ghost_up._replace(spent=self.ghost_up.spent + self.dropped)
        return TreeLedger(
            {"root": ledger(self.root, (gw.up,), {GATEWAY_NODE: up}), "gateway": below},
            {"gateway": link_gap(gw.up, gw.down) + self.ghost_in - self.ghost_out - ghost_spent},
        )


class Kind(Enum):
    ROOT_BEGIN = "root_begin"
    ROOT_DECIDE = "root_decide"
    ROOT_TIMER = "root_timer"
    GATEWAY_COMMAND_TIMER = "gateway_command_timer"
    GATEWAY_RETURN_TIMER = "gateway_return_timer"
    GATEWAY_GIVE_BACK = "gateway_give_back"
    GATEWAY_BEGIN = "gateway_begin"
    GATEWAY_DECIDE = "gateway_decide"
    GATEWAY_TIMER = "gateway_timer"
    NODE_COMMAND_TIMER = "node_command_timer"
    NODE_RETURN_TIMER = "node_return_timer"
    NODE_SPEND = "node_spend"
    NODE_GIVE_BACK = "node_give_back"
    DELIVER = "deliver"
    LOSE = "lose"
    DUPLICATE = "duplicate"
    ROOT_POWER_LOSS = "root_power_loss"
    GATEWAY_POWER_LOSS = "gateway_power_loss"
    GATEWAY_TORN_WRITE = "gateway_torn_write"
    GATEWAY_OLD_COPY = "gateway_old_copy"
    NODE_POWER_LOSS = "node_power_loss"


CHANNEL = frozenset({Kind.DELIVER, Kind.LOSE, Kind.DUPLICATE})
POWER = frozenset(
    {Kind.ROOT_POWER_LOSS, Kind.GATEWAY_POWER_LOSS, Kind.GATEWAY_TORN_WRITE, Kind.NODE_POWER_LOSS}
)
GATEWAY_COPY_NONCE = OLD_COPY_NONCE + 0x80
"""The gateway's n-th old copy starts its upstream role with this nonce + n."""


@dataclass(frozen=True, slots=True)
class ChainStep:
    kind: Kind
    node: int = 0
    units: int = 0
    commit: bool = False
    leg: str = ""
    message: Message | None = None

    def describe(self) -> str:
        text = self.kind.value
        if self.message is not None:
            return f"{text} on the {self.leg} leg: {self.message}"
        if self.node:
            text += f" node {self.node}"
        if self.units:
            text += f" {self.units} unit(s)"
        if self.kind in (Kind.ROOT_DECIDE, Kind.GATEWAY_DECIDE):
            text += " commit" if self.commit else " abort"
        return text


class EarlyGrantGateway(Gateway):
    """Broken on purpose: grants downstream what the upstream intention holds as soon as it
    acknowledges it, and takes it from the commit when that comes."""

    advanced = 0

    def _forwarded(self, before: ClientState, actions: list[Action], now: int) -> list[Action]:
        up, down = self.up.state, self.down.state
        if up.phase is Phase.AWAIT_COMMAND and up.held_amount and not self.advanced:
            self.advanced = up.held_amount
            down = inject_into(down, up.held_amount)
        paid = min(up.usable, self.advanced)
        if paid:
            self.advanced -= paid
            up = evolve(up, usable=up.usable - paid, spent=up.spent + paid)
        assert isinstance(self.down, Below)  # the model's gateways run the Python core
        self.up.state, self.down.state = forward(up, down)
        return actions


class ChainModel:
    def __init__(self, variant: Variant, bounds: ChainBounds, broken: str | None = None) -> None:
        if broken is not None and broken not in BROKEN_RULES:
            raise ValueError(f"unknown broken rule {broken!r} (one of {', '.join(BROKEN_RULES)})")
        self.variant = variant
        self.confirmed_starts = variant.name == "witnessed"
        self.bounds = bounds
        self.broken = broken
        self.timing = bounds.timing()
        self.node_ids = tuple(range(1, bounds.clients + 1))

    def initial(self) -> ChainWorld:
        total = self.bounds.units * UNIT
        root = SupervisorState(total, total, 0, (Session(GATEWAY_NODE),))
        gateway = Gateway(GATEWAY_NODE, self.node_ids, variant=self.variant).state
        nodes = tuple(ClientState(n) for n in self.node_ids)
        older = gateway if self.bounds.old_copies else None
        return ChainWorld(root, gateway, nodes, older=older)

    # -- enumeration -------------------------------------------------------------------------
    def steps(self, w: ChainWorld) -> Iterator[ChainStep]:
        b = self.bounds
        yield from self._supervisor_steps(w.root, w.root_started, "ROOT", unconfirmed(w.root))
        held = w.gateway.up.phase in STARTING or unconfirmed(w.gateway.down)  # Gateway.down.hold
        yield from self._supervisor_steps(w.gateway.down, w.gateway_started, "GATEWAY", held)
        for leg, flight in (("up", w.up), ("down", w.down)):
            for msg, _ in sorted(flight, key=lambda item: message_key(item[0])):
                yield ChainStep(Kind.DELIVER, leg=leg, message=msg)
                if w.lost < b.losses:
                    yield ChainStep(Kind.LOSE, leg=leg, message=msg)
                if w.duplicated < b.duplicates and _frames(flight) < b.in_flight:
                    yield ChainStep(Kind.DUPLICATE, leg=leg, message=msg)
        up = w.gateway.up
        if up.deadline is not None:
            yield ChainStep(Kind.GATEWAY_COMMAND_TIMER)
        if up.return_deadline is not None:
            yield ChainStep(Kind.GATEWAY_RETURN_TIMER)
        rules = self.variant.client
        if w.gateway.down.usable >= UNIT and may_give_back(rules, w.gateway):
            yield ChainStep(Kind.GATEWAY_GIVE_BACK)
        for c in w.nodes:
            if c.deadline is not None:
                yield ChainStep(Kind.NODE_COMMAND_TIMER, c.node)
            if c.return_deadline is not None:
                yield ChainStep(Kind.NODE_RETURN_TIMER, c.node)
            if c.usable >= UNIT and rules.can_spend(c):
                yield ChainStep(Kind.NODE_SPEND, c.node)
                if rules.can_give_back(c):
                    yield ChainStep(Kind.NODE_GIVE_BACK, c.node)
        if w.power_lost < b.power_losses:
            yield ChainStep(Kind.ROOT_POWER_LOSS)
            yield ChainStep(Kind.GATEWAY_POWER_LOSS)
            if w.torn is not None:
                yield ChainStep(Kind.GATEWAY_TORN_WRITE)
        if w.old_copied < b.old_copies and w.older not in (None, w.gateway):
            yield ChainStep(Kind.GATEWAY_OLD_COPY)
            for c in w.nodes:
                yield ChainStep(Kind.NODE_POWER_LOSS, c.node)

    def _supervisor_steps(
        self, st: SupervisorState, started: int, who: str, held: object
    ) -> Iterator[ChainStep]:
        """Begin (not while ``held``: a start waits for books, the gateway for the supervisor
        above), decide, time out."""
        for s in st.sessions:
            if s.phase is Phase.IDLE and started < self.bounds.transactions and not held:
                for units in range(1, min(st.usable // UNIT, self.bounds.units) + 1):
                    yield ChainStep(Kind[f"{who}_BEGIN"], s.node, units=units)
            if s.phase is Phase.ACKED:
                yield ChainStep(Kind[f"{who}_DECIDE"], s.node, commit=True)
                yield ChainStep(Kind[f"{who}_DECIDE"], s.node, commit=False)
            if s.deadline is not None:
                yield ChainStep(Kind[f"{who}_TIMER"], s.node)

    # -- application -------------------------------------------------------------------------
    def apply(self, w: ChainWorld, step: ChainStep) -> ChainWorld | None:
        """The world after ``step``, or None when it leaves the bounds (or the rules refuse it)."""
        k = step.kind
        if k in POWER:
            w = evolve(w, power_lost=w.power_lost + 1)
        elif k is Kind.GATEWAY_OLD_COPY:
            w = evolve(w, old_copied=w.old_copied + 1)
        elif k is Kind.ROOT_BEGIN:
            w = evolve(w, root_started=w.root_started + 1)
        elif k is Kind.GATEWAY_BEGIN:
            w = evolve(w, gateway_started=w.gateway_started + 1)
        try:
            new = self._apply(w, step)
        except LocalProtocolError:  # a BEGIN beyond the witnessed rules' window
            return None
        if new is None or max(_frames(new.up), _frames(new.down)) > self.bounds.in_flight:
            return None
        if new.older is not None and new.old_copied >= self.bounds.old_copies:
            new = evolve(new, older=None)  # no copy left to restore: worlds differing in it merge
        return new

    def _apply(self, w: ChainWorld, step: ChainStep) -> ChainWorld | None:
        k = step.kind
        if k in CHANNEL:
            return self._channel(w, step)
        if k is Kind.ROOT_POWER_LOSS:
            return self._to_root(w, self._start(SUPERVISOR_NONCE + w.power_lost))
        if k in (Kind.ROOT_BEGIN, Kind.ROOT_DECIDE, Kind.ROOT_TIMER):
            return self._to_root(w, _event(step))
        if k is Kind.GATEWAY_TORN_WRITE:  # the upstream file still holds the older record
            assert w.torn is not None
            w = evolve(w, gateway=evolve(w.gateway, up=w.torn), torn=None)
            return self._restart_gateway(w, RESTART_NONCE + w.power_lost)
        if k is Kind.GATEWAY_POWER_LOSS:
            return self._restart_gateway(w, RESTART_NONCE + w.power_lost)
        if k is Kind.GATEWAY_OLD_COPY:
            return self._restart_gateway(self._restored(w), GATEWAY_COPY_NONCE + w.old_copied)
        if k is Kind.GATEWAY_COMMAND_TIMER:
            return self._gateway(w, lambda g: g.fire_command_timer(0))
        if k is Kind.GATEWAY_RETURN_TIMER:
            return self._gateway(w, lambda g: g.fire_return_timer(0))
        if k is Kind.GATEWAY_GIVE_BACK:
            return self._gateway(w, lambda g: g.give_back(UNIT, 0))
        if k in (Kind.GATEWAY_BEGIN, Kind.GATEWAY_DECIDE, Kind.GATEWAY_TIMER):
            return self._to_session(w, step.node, _event(step))
        if k is Kind.NODE_POWER_LOSS:
            return self._to_node(w, step.node, self._start(RESTART_NONCE + w.power_lost))
        return self._to_node(w, step.node, _event(step))

    def _start(self, nonce: int) -> Event:
        """A power loss; a start the rules confirm (witnessed) draws a nonce no start drew."""
        return PowerLoss(nonce) if self.confirmed_starts else POWER_LOSS

    def _restart_gateway(self, w: ChainWorld, nonce: int) -> ChainWorld:
        start = nonce if self.confirmed_starts else None
        sync = SUPERVISOR_NONCE + 0x40 + (nonce & 0x3F) if self.confirmed_starts else 0
        return self._gateway(w, lambda g: g.power_loss(0, start, sync))

    def _restored(self, w: ChainWorld) -> ChainWorld:
        """The gateway's record as it was before its last write comes back; the ledger keeps
        what the copy forgets."""
        older, now = w.older, w.gateway
        assert older is not None
        return evolve(
            w,
            gateway=older,
            ghost_up=restored_ghost(w.ghost_up, now.up, older.up),
            ghost_in=w.ghost_in + now.down.injected - older.down.injected,
            ghost_out=w.ghost_out + now.down.withdrawn - older.down.withdrawn,
            torn=None,
        )

    def _channel(self, w: ChainWorld, step: ChainStep) -> ChainWorld | None:
        msg = step.message
        assert msg is not None
        counts = dict(w.up if step.leg == "up" else w.down)
        if msg not in counts:
            return None
        if step.kind is Kind.DUPLICATE:
            counts[msg] += 1
            w = evolve(w, duplicated=w.duplicated + 1)
        else:
            counts[msg] -= 1
            if not counts[msg]:
                del counts[msg]
        w = evolve(w, **{step.leg: frozenset(counts.items())})
        if step.kind is Kind.DUPLICATE:
            return w
        if step.kind is Kind.LOSE:
            return evolve(w, lost=w.lost + 1)
        return self._receive(w, step.leg, msg)

    def _receive(self, w: ChainWorld, leg: str, msg: Message) -> ChainWorld:
        if msg.TYPE.direction is Direction.TO_CLIENT:
            assert isinstance(msg, ToClient)
            if leg == "up":
                return self._gateway(w, lambda g: g.receive_upstream(msg, 0))
            return self._to_node(w, msg.node, msg)
        assert isinstance(msg, ToSupervisor)
        if leg == "up":
            return self._to_root(w, msg)
        return self._to_session(w, msg.node, msg)

    def _to_root(self, w: ChainWorld, event: Event) -> ChainWorld:
        step = self.variant.supervisor.step(self.timing, w.root.sessions[0], event, 0)
        w = evolve(w, root=apply_session(w.root, 0, step))
        return _sent(w, "up", step.actions)

    def _to_session(self, w: ChainWorld, node: int, event: Event) -> ChainWorld:
        down = w.gateway.down
        step = self.variant.supervisor.step(self.timing, down.sessions[node - 1], event, 0)
        gateway = evolve(w.gateway, down=apply_session(down, node - 1, step))
        w = self._written(w, gateway)
        return _sent(evolve(w, gateway=gateway, torn=None), "down", step.actions)

    def _to_node(self, w: ChainWorld, node: int, event: Event) -> ChainWorld:
        c, actions = self.variant.client.step(self.timing, w.nodes[node - 1], event, 0)
        nodes = (*w.nodes[: node - 1], c, *w.nodes[node:])
        return _sent(evolve(w, nodes=nodes), "down", actions)

    def _gateway(self, w: ChainWorld, act: Any) -> ChainWorld:
        """Run one gateway method on the world's gateway (the live gateway's own code)."""
        cls = EarlyGrantGateway if self.broken == "early-grant" else Gateway
        g = cls(
            GATEWAY_NODE,
            self.node_ids,
            variant=self.variant,
            up_timing=self.timing,
            down_timing=self.timing,
            state=w.gateway,
        )
        if isinstance(g, EarlyGrantGateway):
            g.advanced = w.advanced
        actions = act(g)
        torn = None
        if self.broken == "split-save" and g.state.down != w.gateway.down:
            torn = w.gateway.up if g.state.up != w.gateway.up else None
        advanced = g.advanced if isinstance(g, EarlyGrantGateway) else 0
        w = self._written(w, g.state)
        w = evolve(w, gateway=g.state, advanced=advanced, torn=torn, dropped=w.dropped + g.dropped)
        return _sent(w, "up", actions)

    def _written(self, w: ChainWorld, new: GatewayState) -> ChainWorld:
        """With ``old_copies``: the record before a change is the copy a restore brings back."""
        if w.older is None or new == w.gateway:
            return w
        return evolve(w, older=w.gateway)


def _event(step: ChainStep) -> Event:
    k = step.kind
    if k in (Kind.ROOT_BEGIN, Kind.GATEWAY_BEGIN):
        return Begin(step.units * UNIT)
    if k in (Kind.ROOT_DECIDE, Kind.GATEWAY_DECIDE):
        return Decide(Decision.COMMIT if step.commit else Decision.ABORT)
    if k is Kind.NODE_SPEND:
        return Spend(UNIT)
    if k is Kind.NODE_GIVE_BACK:
        return GiveBack(UNIT)
    if k in (Kind.ROOT_TIMER, Kind.GATEWAY_TIMER):
        return RESPONSE_TIMEOUT
    if k is Kind.NODE_COMMAND_TIMER:
        return COMMAND_TIMEOUT
    return RETURN_TIMEOUT


def _frames(flight: Flight) -> int:
    return sum(n for _, n in flight)


def _sent(w: ChainWorld, leg: str, actions: Any) -> ChainWorld:
    sends = [a.message for a in actions if isinstance(a, Send)]
    if not sends:
        return w
    counts = dict(w.up if leg == "up" else w.down)
    for msg in sends:
        counts[msg] = counts.get(msg, 0) + 1
    return evolve(w, **{leg: frozenset(counts.items())})


@dataclass(slots=True)
class ChainResult:
    bounds: ChainBounds
    broken: str | None
    states: int = 0
    transitions: int = 0
    depth: int = 0
    seconds: float = 0.0
    violations: int = 0
    subsumed: int = 0
    counterexample: list[tuple[ChainStep, ChainWorld]] | None = None
    complete: bool = True
    notes: list[str] = field(default_factory=list)
    variant: str = "hardened"

    def as_json(self) -> dict[str, Any]:
        trace = None
        if self.counterexample is not None:
            trace = [
                {"event": step.describe(), "ledger": w.ledger().as_json()}
                for step, w in self.counterexample
            ]
        return {
            "topology": "chain root -> gateway -> node(s)",
            "rules": self.variant,
            "broken_rule": self.broken,
            "bounds": {k: getattr(self.bounds, k) for k in self.bounds.__slots__},
            "states": self.states,
            "transitions": self.transitions,
            "depth": self.depth,
            "seconds": round(self.seconds, 3),
            "violations": self.violations,
            "subsumed": self.subsumed,
            "complete": self.complete,
            "counterexample": trace,
        }


Counters = tuple[int, int, int, int, int, int]


def _counters(w: ChainWorld) -> Counters:
    return (w.root_started, w.gateway_started, w.lost, w.duplicated, w.power_lost, w.old_copied)


class _Subsumption:
    """A world is skipped when the same protocol state was stored with every run counter (a
    budget) lower or equal: it can do all this one can (see ``reduce``)."""

    def __init__(self) -> None:
        self.seen: dict[ChainWorld, list[Counters]] = {}
        self.subsumed = 0

    def admit(self, w: ChainWorld) -> bool:
        key = evolve(
            w, root_started=0, gateway_started=0, lost=0, duplicated=0, power_lost=0, old_copied=0
        )
        mine = _counters(w)
        stored = self.seen.setdefault(key, [])
        if any(all(a <= b for a, b in zip(old, mine, strict=True)) for old in stored):
            self.subsumed += 1
            return False
        stored.append(mine)
        return True


def check_chain(
    variant: str = "hardened",
    bounds: ChainBounds | None = None,
    *,
    broken: str | None = None,
    max_states: int | None = None,
    stop_at_first: bool = False,
    progress: Callable[[int, int, float], None] | None = None,
) -> ChainResult:
    """Breadth-first over every reachable world; a counterexample found is a shortest one."""
    b = bounds or ChainBounds()
    model = ChainModel(get_variant(variant), b, broken)
    reducer = _Subsumption()

    def successors(world: ChainWorld) -> Iterator[tuple[ChainStep, ChainWorld]]:
        for step in model.steps(world):
            nxt = model.apply(world, step)
            if nxt is not None:
                yield step, nxt

    search = breadth_first(
        model.initial(),
        successors,
        admit=reducer.admit,
        violates=lambda world: not world.passive(),
        max_states=max_states,
        stop_at_first=stop_at_first,
        progress=progress,
    )
    result = ChainResult(b, broken, search.states, search.transitions, search.depth)
    result.variant = variant
    result.seconds, result.violations, result.subsumed = (
        search.seconds,
        search.violations,
        reducer.subsumed,
    )
    result.complete, result.notes = search.complete, search.notes
    if search.first_violation is not None:
        result.counterexample = search.path(search.first_violation)
    return result


def format_chain(result: ChainResult, trace: bool = False) -> str:
    b = result.bounds
    rule = f", gateway rule broken: {result.broken}" if result.broken else ""
    copies = f", {b.old_copies} old cop(ies) of the gateway's record" if b.old_copies else ""
    lines = [
        f"chain root -> gateway -> {b.clients} node(s), {result.variant} rules{rule}",
        f"bounds: {b.transactions} transaction(s) per supervisor, {b.losses} loss(es), "
        f"{b.duplicates} duplicate(s), {b.power_losses} power loss(es) (root, gateway or node)"
        f"{copies}, "
        f"{b.in_flight} frame(s) in flight per leg, {b.units} unit(s), {b.retries} retries",
        f"{result.states:,} states ({result.subsumed:,} subsumed), {result.transitions:,} "
        f"transitions, depth {result.depth}, {result.seconds:.1f} s"
        + ("" if result.complete else " (incomplete: " + "; ".join(result.notes) + ")"),
    ]
    if not result.violations:
        lines.append("PASSIVE: no level of the tree and no gateway created energy")
        return "\n".join(lines)
    lines.append(f"VIOLATION: energy created in {result.violations} state(s)")
    if trace and result.counterexample is not None:
        for i, (step, world) in enumerate(result.counterexample, 1):
            tree = world.ledger()
            levels = ", ".join(
                f"{name} {led.dissipated:+d} µJ" for name, led in tree.levels.items()
            )
            gaps = ", ".join(f"{name} gap {gap:+d} µJ" for name, gap in tree.link_gaps.items())
            lines.append(f"  {i:2d}. {step.describe()}  [dissipated: {levels}; {gaps}]")
    return "\n".join(lines)
