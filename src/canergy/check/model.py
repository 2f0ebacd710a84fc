"""The joint state of supervisor, clients and channel, and every step that can change it.

Time is abstract: the rules run with zero timeouts and ``now = 0``, so an armed deadline is 0 and
a timer fires only when a step says so. Energies are whole wire quanta ("units").

An attacker on the bus (``Bounds.forgeries``, ``Bounds.replays``) sends a frame that its receiver
takes at once: a CAN frame reaches every node when it is sent, and the attacker chooses when to
send, so no delay is lost and its frames take no in-flight capacity.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from enum import Enum

from canergy.check.attacker import forgeable
from canergy.core import witnessed
from canergy.core.actions import Send
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import (
    COMMAND_TIMEOUT,
    POWER_LOSS,
    RESPONSE_TIMEOUT,
    RETURN_TIMEOUT,
    Begin,
    BooksLost,
    Decide,
    GiveBack,
    PowerLoss,
    Spend,
)
from canergy.core.state import ClientState, Decision, Phase, Session, SupervisorState
from canergy.core.steps import Actions, SessionStep
from canergy.core.supervisor import apply_session, unconfirmed
from canergy.core.table import Event
from canergy.core.timing import Timing
from canergy.core.variants import Variant
from canergy.frozen import evolve
from canergy.ledger import NOT_LOST, Ledger, LostRecord, ledger
from canergy.messages import QUANTUM_UJ, Direction, Message, ToClient, ToSupervisor

UNIT = QUANTUM_UJ
RESTART_NONCE = 0x100
"""A client's n-th power loss of a run restarts it with nonce ``RESTART_NONCE + n``, and its n-th
old copy with ``OLD_COPY_NONCE + n`` (JOIN nonces are 1, 2...): every start draws a nonce no
earlier start drew, as a random 16-bit one does but for a chance of 2^-16 (rules that confirm a
start, ``witnessed``, use it; the others ignore it)."""
OLD_COPY_NONCE = 0x200
SUPERVISOR_NONCE = 0x300
"""The supervisor's n-th start of a run (a power loss, or with ``SUPERVISOR_COPY_NONCE`` an old
copy) sends SYNC with nonce ``SUPERVISOR_NONCE + n``: no earlier start drew it (rules that have
every start confirmed, ``witnessed``, use it)."""
SUPERVISOR_COPY_NONCE = 0x380
RESYNC_NONCE = 0x3C0
"""The supervisor's n-th re-sync of a node in a run sends SYNC with nonce ``RESYNC_NONCE + n``
(the live supervisor draws a fresh random one for each): no start or other re-sync drew it."""
WINDOW = 1
"""The checker's window B (``Timing.window``): 1, so that it binds within the bounds."""
Flight = frozenset[tuple[Message, int]]
"""The multiset of frames in flight as (message, copies): canonical without sorting."""


@dataclass(frozen=True, slots=True)
class Bounds:
    """What the exploration may spend. Energies in units (1 unit = 1 mJ)."""

    clients: int = 1
    transactions: int = 2
    losses: int = 1
    duplicates: int = 1
    power_losses: int = 1
    in_flight: int = 3
    units: int = 1
    retries: int = 1
    timeouts: int | None = None
    """Timer expiries (either side) in one run; None: unbounded (and not counted)."""
    nv_losses: int = 0
    """Client starts with both NV slots unreadable (new, wiped or corrupted record)."""
    old_copies: int = 0
    """Client starts with its record replaced by the one before its last write."""
    backups: bool = False
    """With ``old_copies``: the old copy is a backup taken at any earlier moment (a step of its
    own, ``client_nv_backup``), not the record before the node's last write."""
    supervisor_old_copies: int = 0
    """Supervisor starts from its state file as it was before its last write (a backup or a
    snapshot put back)."""
    supervisor_backups: bool = False
    """With ``supervisor_old_copies``: the old state file is a backup taken at any earlier moment
    (a step of its own, ``supervisor_backup``, offered while a restore is left), not the state
    before the supervisor's last write."""
    forgeries: int = 0
    """Frames a keyless attacker builds and sends (``attacker.forgeable``; the codec is public)."""
    replays: int = 0
    """Copies of frames seen earlier on the bus an attacker sends again (authenticated mode)."""
    resyncs: int = 0
    """Re-syncs of one idle node by the supervisor (``witnessed.resync_session``, what the live
    supervisor does when a begin is refused as beyond the window or a node's counts are
    ignored), each with a fresh SYNC nonce; at any moment the node's session is IDLE, window
    closed or not (witnessed rules only)."""
    returns: bool = True
    spending: bool = True
    extra_ids: int = 2
    """Paper variant: intentions it may re-define beyond ``transactions`` (ids are unbounded)."""

    def timing(self) -> Timing:
        return Timing(
            response_timeout_us=0,
            retries=self.retries,
            command_timeout_us=0,
            return_retry_us=0,
            window=WINDOW,
        )


@dataclass(frozen=True, slots=True)
class World:
    sup: SupervisorState
    clients: tuple[ClientState, ...]
    flight: Flight
    started: int = 0
    lost: int = 0
    duplicated: int = 0
    power_lost: int = 0
    timed_out: int = 0
    nv_lost: int = 0
    old_copied: int = 0
    older: tuple[ClientState, ...] = ()
    """Each client's state before its last record write (kept only when old copies are on)."""
    sup_older: SupervisorState | None = None
    """The supervisor's state before its last record write (kept only when its old copies are
    on)."""
    sup_old_copied: int = 0
    resynced: int = 0
    lost_records: tuple[tuple[int, LostRecord], ...] = ()
    """Nodes that lost their record, and what the observer saw it hold (for the ledger)."""
    forged: int = 0
    replayed: int = 0
    seen: frozenset[Message] = frozenset()
    """Every frame sent on the bus so far (kept only when replays are on): what can be replayed.
    Forged frames are not energy: the ledger counts only the nodes' states."""

    def frames(self) -> int:
        return sum(n for _, n in self.flight)

    def ledger(self) -> Ledger:
        return ledger(self.sup, self.clients, dict(self.lost_records))

    def quiescent(self) -> bool:
        """No transaction open, nothing in flight, no return waiting."""
        return (
            not self.flight
            and all(s.phase is Phase.IDLE for s in self.sup.sessions)
            and all(
                c.return_pending == 0 or c.return_seq <= s.returns_credited
                for s, c in zip(self.sup.sessions, self.clients, strict=True)
            )
        )


class StepKind(Enum):
    """The kinds of nondeterministic choice (values are the names used in JSON traces)."""

    BEGIN = "begin"
    DECIDE = "decide"
    DELIVER = "deliver"
    LOSE = "lose"
    DUPLICATE = "duplicate"
    SUPERVISOR_TIMER = "supervisor_timer"
    COMMAND_TIMER = "command_timer"
    RETURN_TIMER = "return_timer"
    SPEND = "spend"
    GIVE_BACK = "give_back"
    CLIENT_POWER_LOSS = "client_power_loss"
    SUPERVISOR_POWER_LOSS = "supervisor_power_loss"
    NV_LOST = "client_nv_lost"
    NV_OLD_COPY = "client_nv_old_copy"
    NV_BACKUP = "client_nv_backup"
    SUPERVISOR_OLD_COPY = "supervisor_old_copy"
    SUPERVISOR_BACKUP = "supervisor_backup"
    FORGE = "forge"
    REPLAY = "replay"
    RESYNC = "resync"


K = StepKind
CHANNEL_KINDS = frozenset({K.DELIVER, K.LOSE, K.DUPLICATE})
TIMER_KINDS = frozenset({K.SUPERVISOR_TIMER, K.COMMAND_TIMER, K.RETURN_TIMER})
SUPERVISOR_KINDS = frozenset({K.BEGIN, K.DECIDE, K.SUPERVISOR_TIMER, K.RESYNC})
POWER_LOSS_KINDS = frozenset({K.CLIENT_POWER_LOSS, K.SUPERVISOR_POWER_LOSS})
ATTACKER_KINDS = frozenset({K.FORGE, K.REPLAY})


@dataclass(frozen=True, slots=True)
class Step:
    """One nondeterministic choice. ``node`` is the node concerned, when there is one."""

    kind: StepKind
    node: int = 0
    units: int = 0
    commit: bool = False
    message: Message | None = None
    nonce: int = 0

    def describe(self) -> str:
        kind = self.kind.value
        if self.message is not None:
            return f"{kind} {self.message}"
        extra = {
            K.BEGIN: f" {self.units} unit(s)",
            K.DECIDE: " commit" if self.commit else " abort",
            K.NV_LOST: f" (nonce {self.nonce})",
            K.RESYNC: f" (nonce {self.nonce:#x})",
        }
        where = f" node {self.node}" if self.node else ""
        return f"{kind}{where}{extra.get(self.kind, '')}"


def initial_world(bounds: Bounds) -> World:
    nodes = range(1, bounds.clients + 1)
    total = bounds.units * UNIT
    sup = SupervisorState(total, total, 0, tuple(Session(n) for n in nodes))
    clients = tuple(ClientState(n) for n in nodes)
    return World(
        sup,
        clients,
        frozenset(),
        older=clients if bounds.old_copies else (),
        sup_older=sup if bounds.supervisor_old_copies else None,
    )


class Model:
    """Steps of one variant under one set of bounds."""

    def __init__(self, variant: Variant, bounds: Bounds) -> None:
        self.variant = variant
        self.bounds = bounds
        self.timing = bounds.timing()
        b = bounds
        self.tx_limit = b.transactions + b.extra_ids
        """The highest transaction number a world may reach: what begins, and with the rules
        that lift it at a start (``witnessed``) one window per start or frame that lifts it."""
        if variant.lifts_tx:
            lifts = b.power_losses + b.supervisor_old_copies + b.old_copies + b.duplicates + 1
            lifts += b.resyncs  # a re-synced node settles B further: tx moves up to its ltx
            self.tx_limit += self.timing.window * lifts

    # -- enumeration -----------------------------------------------------------------
    def steps(self, w: World) -> Iterator[Step]:
        b = self.bounds
        may_time_out = b.timeouts is None or w.timed_out < b.timeouts
        may_lose_power = w.power_lost < b.power_losses
        waiting = bool(unconfirmed(w.sup))
        may_resync = w.resynced < b.resyncs and self.variant.lifts_tx
        for s in w.sup.sessions:
            if s.phase is Phase.IDLE and w.started < b.transactions and not waiting:
                for units in range(1, min(w.sup.usable // UNIT, b.units) + 1):
                    yield Step(K.BEGIN, s.node, units=units)
            if s.phase is Phase.ACKED:
                yield Step(K.DECIDE, s.node, commit=True)
                yield Step(K.DECIDE, s.node, commit=False)
            if s.deadline is not None and may_time_out:
                yield Step(K.SUPERVISOR_TIMER, s.node)
            if s.phase is Phase.IDLE and may_resync:
                yield Step(K.RESYNC, s.node, nonce=RESYNC_NONCE + w.resynced + 1)
        for msg, _ in sorted(w.flight, key=_flight_key):
            yield Step(K.DELIVER, message=msg)
            if w.lost < b.losses:
                yield Step(K.LOSE, message=msg)
            if w.duplicated < b.duplicates and w.frames() < b.in_flight:
                yield Step(K.DUPLICATE, message=msg)
        for c in w.clients:
            if c.deadline is not None and may_time_out:
                yield Step(K.COMMAND_TIMER, c.node)
            if c.return_deadline is not None and may_time_out:
                yield Step(K.RETURN_TIMER, c.node)
            if b.spending and c.usable >= UNIT and self.variant.client.can_spend(c):
                yield Step(K.SPEND, c.node)
            if b.returns and c.usable >= UNIT and self.variant.client.can_give_back(c):
                yield Step(K.GIVE_BACK, c.node)
            if may_lose_power:
                yield Step(K.CLIENT_POWER_LOSS, c.node, nonce=RESTART_NONCE + w.power_lost + 1)
            if w.nv_lost < b.nv_losses:
                yield Step(K.NV_LOST, c.node, nonce=w.nv_lost + 1)
            if w.old_copied < b.old_copies and w.older[c.node - 1] != c:
                yield Step(K.NV_OLD_COPY, c.node, nonce=OLD_COPY_NONCE + w.old_copied + 1)
            if b.backups and b.old_copies and w.older[c.node - 1] != c:
                yield Step(K.NV_BACKUP, c.node)
        if may_lose_power:
            yield Step(K.SUPERVISOR_POWER_LOSS)
        if w.sup_old_copied < b.supervisor_old_copies and w.sup_older not in (None, w.sup):
            yield Step(K.SUPERVISOR_OLD_COPY)
            if b.supervisor_backups:
                yield Step(K.SUPERVISOR_BACKUP)
        if w.forged < b.forgeries:
            for msg in forgeable(self.variant, w.sup.sessions, w.clients, b.units):
                yield Step(K.FORGE, message=msg)
        if w.replayed < b.replays:
            for msg in sorted(w.seen, key=message_key):
                yield Step(K.REPLAY, message=msg)

    # -- application -----------------------------------------------------------------
    def apply(self, w: World, step: Step) -> World | None:
        """The world after ``step``, or None when it leaves the bounds (or the rules refuse a
        BEGIN: beyond the witnessed rules' window)."""
        try:
            new = self._apply(self.charge(w, step.kind), step)
        except LocalProtocolError:
            if step.kind is not K.BEGIN:
                raise
            return None
        return new if new is not None and self.within(new) else None

    def within(self, w: World) -> bool:
        """Within the frames in flight and the transaction ids the bounds allow."""
        limit = self.tx_limit
        return w.frames() <= self.bounds.in_flight and all(s.tx <= limit for s in w.sup.sessions)

    def charge(self, w: World, kind: StepKind) -> World:
        """Charge the step to the bounds it uses."""
        if kind in TIMER_KINDS and self.bounds.timeouts is not None:
            return evolve(w, timed_out=w.timed_out + 1)
        if kind in POWER_LOSS_KINDS:
            return evolve(w, power_lost=w.power_lost + 1)
        if kind is K.BEGIN:
            return evolve(w, started=w.started + 1)
        if kind is K.NV_LOST:
            return evolve(w, nv_lost=w.nv_lost + 1)  # the ghost Rc is kept in _apply
        if kind is K.NV_OLD_COPY:
            return evolve(w, old_copied=w.old_copied + 1)
        if kind is K.SUPERVISOR_OLD_COPY:
            return evolve(w, sup_old_copied=w.sup_old_copied + 1)
        if kind is K.FORGE:
            return evolve(w, forged=w.forged + 1)
        if kind is K.REPLAY:
            return evolve(w, replayed=w.replayed + 1)
        if kind is K.RESYNC:
            return evolve(w, resynced=w.resynced + 1)
        return w

    def _apply(self, w: World, step: Step) -> World | None:
        """Every step but the channel's is one event fed to one table: the rules the demo runs."""
        if step.kind in CHANNEL_KINDS:
            return self._channel(w, step)
        if step.kind in ATTACKER_KINDS:
            return self._attack(w, step)
        if step.kind is K.SUPERVISOR_BACKUP:  # a copy of the state file as it is now
            return evolve(w, sup_older=w.sup)
        if step.kind is K.SUPERVISOR_OLD_COPY and w.sup_older is not None:
            w = evolve(w, sup=w.sup_older)  # the old state file comes back; it restarts from it
        if step.kind in (K.SUPERVISOR_POWER_LOSS, K.SUPERVISOR_OLD_COPY):
            return self.restart(w, supervisor_nonce(step.kind, w.power_lost, w.sup_old_copied))
        i = step.node - 1
        if step.kind is K.NV_LOST:
            c, lost = w.clients[i], dict(w.lost_records)
            before = lost.get(step.node, NOT_LOST)
            lost[step.node] = LostRecord(max(c.credited, before.credited), c.spent + before.spent)
            w = evolve(w, lost_records=tuple(sorted(lost.items())))
        if step.kind is K.NV_BACKUP:  # a copy of the record as it is now
            return evolve(w, older=(*w.older[:i], w.clients[i], *w.older[i + 1 :]))
        if step.kind is K.NV_OLD_COPY:  # the old record comes back; the node restarts from it
            c, older, lost = w.clients[i], w.older[i], dict(w.lost_records)
            lost[step.node] = restored_ghost(lost.get(step.node, NOT_LOST), c, older)
            clients = (*w.clients[:i], older, *w.clients[i + 1 :])
            w = evolve(w, clients=clients, lost_records=tuple(sorted(lost.items())))
            return self._to_client(w, i, PowerLoss(step.nonce))
        if step.kind in SUPERVISOR_KINDS:
            return self._to_session(w, i, self.event(step))
        event = self.event(step)
        assert not isinstance(event, Resync)  # a supervisor's step
        return self._to_client(w, i, event)

    @staticmethod
    def event(step: Step) -> Event | Resync:
        """The event a step that is neither the channel's nor the attacker's feeds its node."""
        kind = step.kind
        if kind is K.RESYNC:
            return Resync(step.nonce)
        if kind is K.BEGIN:
            return Begin(step.units * UNIT)
        if kind is K.DECIDE:
            return Decide(Decision.COMMIT if step.commit else Decision.ABORT)
        if kind is K.SPEND:
            return Spend(UNIT)
        if kind is K.GIVE_BACK:
            return GiveBack(UNIT)
        if kind is K.NV_LOST:
            return BooksLost(step.nonce)
        if kind is K.CLIENT_POWER_LOSS:
            return PowerLoss(step.nonce)
        return _DATALESS[kind]

    def _channel(self, w: World, step: Step) -> World | None:
        msg = step.message
        assert msg is not None
        counts = dict(w.flight)
        if msg not in counts:
            return None
        if step.kind is K.DUPLICATE:
            counts[msg] += 1
            return evolve(w, flight=frozenset(counts.items()), duplicated=w.duplicated + 1)
        counts[msg] -= 1
        if not counts[msg]:
            del counts[msg]
        w = evolve(w, flight=frozenset(counts.items()))
        if step.kind is K.LOSE:
            return evolve(w, lost=w.lost + 1)
        return self._receive(w, msg)

    def _attack(self, w: World, step: Step) -> World | None:
        """The attacker sends a frame it may send now; its receiver takes it at once."""
        msg, b = step.message, self.bounds
        assert msg is not None
        if w.forged > b.forgeries or w.replayed > b.replays:  # ``charge`` counted the step
            return None
        if step.kind is K.REPLAY and msg not in w.seen:
            return None
        if step.kind is K.FORGE:
            if msg not in forgeable(self.variant, w.sup.sessions, w.clients, b.units):
                return None
            if b.replays:  # a forged frame has been on the bus: it can be replayed too
                w = evolve(w, seen=w.seen | {msg})
        return self._receive(w, msg)

    def _receive(self, w: World, msg: Message) -> World:
        """``msg`` arrives at its receiver."""
        i = msg.node - 1
        if msg.TYPE.direction is Direction.TO_CLIENT:
            assert isinstance(msg, ToClient)
            return self._to_client(w, i, msg)
        assert isinstance(msg, ToSupervisor)
        return self._to_session(w, i, msg)

    def restart(self, w: World, nonce: int) -> World:
        """A supervisor start: every session restarts; the state file is written once, after
        them all (the copy before it is kept when it changed, unless copies are backups)."""
        before, older = w.sup, w.sup_older
        for i in range(len(w.sup.sessions)):
            w = self.restart_session(w, i, nonce)
        if older is None or self.bounds.supervisor_backups:
            return w
        rules = self.variant.supervisor
        wrote = w.sup.usable != before.usable or any(
            rules.persistent(a) != rules.persistent(b)
            for a, b in zip(before.sessions, w.sup.sessions, strict=True)
        )
        return evolve(w, sup_older=before if wrote else older)

    def restart_session(self, w: World, i: int, nonce: int = 0) -> World:
        """Session ``i``'s share of a supervisor start (it touches no other node)."""
        return self._to_session(w, i, PowerLoss(nonce) if nonce else POWER_LOSS)

    def _to_session(self, w: World, i: int, event: Event | Resync) -> World:
        rules = self.variant.supervisor
        old = w.sup.sessions[i]
        step = session_step(self.variant, self.timing, old, event)
        if (
            w.sup_older is not None
            and not self.bounds.supervisor_backups
            and (step.credit or rules.persistent(old) != rules.persistent(step.session))
        ):
            w = evolve(w, sup_older=w.sup)
        return self._out(evolve(w, sup=apply_session(w.sup, i, step)), step.actions)

    def _to_client(self, w: World, i: int, event: Event) -> World:
        rules = self.variant.client
        old = w.clients[i]
        c, actions = rules.step(self.timing, old, event, 0)
        clients = (*w.clients[:i], c, *w.clients[i + 1 :])
        if w.older and not self.bounds.backups and rules.persistent(old) != rules.persistent(c):
            w = evolve(w, older=(*w.older[:i], old, *w.older[i + 1 :]))
        return self._out(evolve(w, clients=clients), actions)

    def _out(self, w: World, actions: Actions) -> World:
        sends = [a.message for a in actions if isinstance(a, Send)]
        if not sends:
            return w
        counts = dict(w.flight)
        for msg in sends:
            counts[msg] = counts.get(msg, 0) + 1
        if self.bounds.replays:
            w = evolve(w, seen=w.seen.union(sends))
        return evolve(w, flight=frozenset(counts.items()))


@dataclass(frozen=True, slots=True)
class Resync:
    """The supervisor re-syncs one idle node with SYNC nonce ``nonce``: a call of its own
    (``Supervisor.resync``, ``witnessed.resync_session``), not a cell of the table."""

    nonce: int


def session_step(variant: Variant, t: Timing, s: Session, event: Event | Resync) -> SessionStep:
    """What the supervisor does with ``event`` for session ``s`` (no time: ``now = 0``)."""
    if isinstance(event, Resync):
        return witnessed.resync_session(t, s, event.nonce, 0)
    return variant.supervisor.step(t, s, event, 0)


_DATALESS: dict[StepKind, Event] = {
    K.SUPERVISOR_TIMER: RESPONSE_TIMEOUT,
    K.COMMAND_TIMER: COMMAND_TIMEOUT,
    K.RETURN_TIMER: RETURN_TIMEOUT,
}
"""The events of steps that carry no data."""


def supervisor_nonce(kind: StepKind, power_lost: int, old_copied: int) -> int:
    """The SYNC nonce of a supervisor start, from the run counters once the step is charged."""
    if kind is K.SUPERVISOR_OLD_COPY:
        return SUPERVISOR_COPY_NONCE + old_copied
    return SUPERVISOR_NONCE + power_lost


def restored_ghost(before: LostRecord, c: ClientState, older: ClientState) -> LostRecord:
    """What the observer keeps when a node's record is replaced by an older copy: the largest
    Rc seen, and what the actuator used after the copy was written (the copy forgets it)."""
    return LostRecord(max(c.credited, before.credited), before.spent + c.spent - older.spent)


def _flight_key(item: tuple[Message, int]) -> tuple[int, str]:
    return message_key(item[0])


def message_key(msg: Message) -> tuple[int, str]:
    return (int(msg.TYPE), repr(msg))


def replay(model: Model, steps: list[Step]) -> list[World]:
    """Re-run ``steps`` from the initial world through the core; the worlds after each step."""
    worlds = [initial_world(model.bounds)]
    for step in steps:
        nxt = model.apply(worlds[-1], step)
        if nxt is None:
            raise ValueError(f"step not applicable: {step.describe()}")
        worlds.append(nxt)
    return worlds[1:]
