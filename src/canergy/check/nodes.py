"""Node contents, interned, and their moves, worked out once per content and position.

What one node holds — its session, its client record, the frames to and from it, its older
record and lost record (when the bounds keep them) and the frames seen for it — is its
*content*: a tuple of part numbers (``parts``), itself numbered. A world is the supervisor's
usable budget, the run counters and one content per node; the content at position ``p`` is node
``p + 1``'s.

Every step but a supervisor power loss changes one node only, and a supervisor power loss
restarts each session on its own. So the moves of a content at a position are listed once, as
``Model.steps`` lists them, and each move's result is worked out on first use as
``Model.apply`` works it out, with the core's rules memoized per part (``Parts``). The steps'
conditions on the run counters are left to ``packed.Guards``, checked per world.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, cast

from canergy.check.attacker import forgeable
from canergy.check.model import (
    ATTACKER_KINDS,
    CHANNEL_KINDS,
    OLD_COPY_NONCE,
    RESTART_NONCE,
    RESYNC_NONCE,
    SUPERVISOR_KINDS,
    UNIT,
    Model,
    Resync,
    Step,
    StepKind,
    World,
    message_key,
    restored_ghost,
    supervisor_nonce,
)
from canergy.check.packed import NODE_BITS, Guards, Layout
from canergy.check.parts import Parts
from canergy.check.reduce import (
    NodeKey,
    Signature,
    compose_key,
    frames_key,
    seen_key,
    signature,
)
from canergy.core.errors import LocalProtocolError
from canergy.core.inputs import POWER_LOSS, PowerLoss
from canergy.core.state import ClientState, Phase, SupervisorState
from canergy.core.table import Event
from canergy.ledger import NOT_LOST, LostRecord, start_waits

K = StepKind


class Content(NamedTuple):
    """One node's part of a world, as part numbers (``older`` -1: not kept)."""

    session: int
    client: int
    flight: int
    older: int
    ghost: LostRecord | None
    seen: int


Result = tuple[int, int, int, int]
"""A move's result: (content after, credit to Us, counters charged (packed), frames added)."""
INVALID: Result = (-1, 0, 0, 0)
"""The move leaves the bounds (``Model.apply`` gives None)."""


Move = list[Any]
"""One step of one content at one position: ``[result, guard, position, content, spec]``, the
result (``Result``) filled on first use. A list, not an object: a search makes millions."""
RESULT, GUARD, POS, CONTENT, SPEC = range(5)


Keyed = tuple[tuple[int, str], int, Move]
"""A move ordered by its frame's ``message_key`` (then its place among that frame's moves)."""
Listed = tuple[tuple[int, str], StepKind, int]
"""A step of one part, for any content holding it: (its frame's key, kind, argument)."""
Spec = tuple[tuple[int, str], int, StepKind, int, int, "Event | Resync | int | None", int]
"""The same with what applying it needs: (frame's key, guard, kind, argument, counters charged
(packed), the event it feeds (a number: a frame), the side it goes to (``SESSION``...))."""
CHANNEL, SESSION, CLIENT = range(3)
"""Where a step's event goes: none (the channel alone), the node's session, its client."""
NO_KEY = (0, "")
"""The key of a step that is not a frame's."""


class NodeMoves:
    """The moves of one content at one position, in ``Model.steps`` order within each section:
    its session's, its frames' (keyed, to merge with the other nodes'), its client's, its
    session's share of a supervisor power loss, the forger's and the replayer's frames."""

    __slots__ = (
        "attacks",
        "client",
        "flight",
        "flight_moves",
        "forge",
        "replay",
        "restart",
        "session",
    )

    def __init__(self, restart: list[Move]) -> None:
        self.session: list[Move] = []
        self.flight: list[Keyed] = []
        self.flight_moves: list[Move] = []
        """The frames' moves alone (when no other node has frames in flight)."""
        self.client: list[Move] = []
        self.restart = restart
        """A supervisor power loss: its share, by how many power losses came before."""
        self.forge: list[Move] = []
        self.replay: list[Keyed] = []
        self.attacks = False
        """Whether the attacker has moves here (forged or replayed frames)."""


class NodeTable:
    """Interned contents with what a world needs of each — its symmetry key, its share of the
    ledger's held energy, whether it is quiescent, its frames in flight — and their moves."""

    def __init__(self, model: Model, layout: Layout, guards: Guards) -> None:
        self.model = model
        self.bounds = b = model.bounds
        self.guards = guards
        self.parts = Parts(model)
        self.charge = layout.charges(model)
        self.total = b.units * UNIT
        self.tx_limit = model.tx_limit
        self.contents: list[Content] = []
        self.ids: dict[Content, int] = {}
        self.keys: list[NodeKey] = []
        self.held: list[int] = []
        """The node's share of the ledger's held energy (its Ts, Uc, spent and return in flight,
        less the overlap): the ledger is a sum over nodes plus Us."""
        self.quiet: list[bool] = []
        self.syncing: list[bool] = []
        """The node's session waits for its books in a start (witnessed; not a re-sync): the
        ledger counts none of Us (``ledger.supervisor_usable``) and no grant goes to anyone
        (``unconfirmed``)."""
        self.frames: list[int] = []
        self.bare: list[int] = []
        """The same content with nothing seen (subsumption compares what was seen apart)."""
        self.seen: list[int] = []
        """The frames seen, as a bit mask."""
        self.moves: list[list[NodeMoves | None]] = [[] for _ in range(b.clients)]
        self._seen_bits: dict[int, int] = {}
        self._signatures: dict[int, Signature] = {}
        self._flight_keys: dict[int, tuple[list[tuple[Signature, int]], int]] = {}
        self._seen_keys: dict[int, list[Signature]] = {}
        self._solo: dict[tuple[int, int, LostRecord | None], tuple[int, bool]] = {}
        self._specs: dict[tuple[object, ...], list[Spec]] = {}
        self._wrote: dict[tuple[int, int], bool] = {}
        self._restored: dict[tuple[int, int, int, int], Result] = {}

    # -- contents ----------------------------------------------------------------------
    def intern(self, c: Content) -> int:
        i = self.ids.get(c)
        if i is not None:
            return i
        bare = None
        if c.seen != self.parts.empty_seen:
            bare = self.intern(c._replace(seen=self.parts.empty_seen))
        i = self.ids[c] = len(self.contents)
        if i >> NODE_BITS:
            raise OverflowError("more node contents than a world's code has room for")
        self.contents.append(c)
        flight_key, frames = self._flight_key(c.flight)
        older = None if c.older < 0 else self._signature(c.older)
        self.keys.append(
            compose_key(
                self._signature(c.session),
                self._signature(c.client),
                flight_key,
                older,
                c.ghost,
                self._seen_key(c.seen),
            )
        )
        held, quiet = self._held_and_quiet(c.session, c.client, c.ghost)
        self.held.append(held)
        self.quiet.append(quiet and not frames)
        session = self.parts.objects[c.session]
        self.syncing.append(start_waits(session))
        self.frames.append(frames)
        mask = 0
        for frame in self.parts.seens[c.seen]:
            mask |= 1 << self._seen_bits.setdefault(frame, len(self._seen_bits))
        self.seen.append(mask)
        self.bare.append(i if bare is None else bare)
        for row in self.moves:
            row.append(None)
        return i

    def _signature(self, part: int) -> Signature:
        sig = self._signatures.get(part)
        if sig is None:
            sig = self._signatures[part] = signature(self.parts.objects[part])
        return sig

    def _flight_key(self, flight: int) -> tuple[list[tuple[Signature, int]], int]:
        """The flight's part of the symmetry key, and its number of frames."""
        out = self._flight_keys.get(flight)
        if out is None:
            items = [(self.parts.objects[m], n) for m, n in self.parts.flights[flight]]
            out = self._flight_keys[flight] = (frames_key(items), sum(n for _, n in items))
        return out

    def _seen_key(self, seen: int) -> list[Signature]:
        out = self._seen_keys.get(seen)
        if out is None:
            out = self._seen_keys[seen] = seen_key(
                self.parts.objects[m] for m in self.parts.seens[seen]
            )
        return out

    def _held_and_quiet(
        self, session: int, client: int, ghost: LostRecord | None
    ) -> tuple[int, bool]:
        """The node's held energy and whether it is quiescent (frames aside), as ``World.ledger``
        and ``World.quiescent`` see a world of this node alone with Us 0."""
        key = (session, client, ghost)
        out = self._solo.get(key)
        if out is None:
            solo = World(
                SupervisorState(0, 0, 0, (self.parts.objects[session],)),
                (self.parts.objects[client],),
                frozenset(),
                lost_records=() if ghost is None else ((1, ghost),),
            )
            out = self._solo[key] = (solo.ledger().held, solo.quiescent())
        return out

    def content_of(self, w: World, p: int) -> Content:
        """What node ``p + 1`` holds in ``w``."""
        n, part = p + 1, self.parts.part
        return Content(
            part(w.sup.sessions[p]),
            part(w.clients[p]),
            self.parts.flight(tuple((part(m), k) for m, k in w.flight if m.node == n)),
            part(w.older[p]) if w.older else -1,
            dict(w.lost_records).get(n),
            self.parts.seen(tuple(part(m) for m in w.seen if m.node == n)),
        )

    def objects(self, c: int, n: int) -> _Objects:
        """Content ``c`` as node ``n``'s objects."""
        x, named = self.contents[c], self.parts.named
        return _Objects(
            named(x.session, n),
            named(x.client, n),
            [(named(m, n), k) for m, k in self.parts.flights[x.flight]],
            None if x.older < 0 else named(x.older, n),
            x.ghost,
            [named(m, n) for m in self.parts.seens[x.seen]],
        )

    def world(
        self,
        usable: int,
        nodes: list[int],
        counted: tuple[int, ...],
        older: tuple[int, tuple[int, ...]] | None = None,
    ) -> World:
        """The reference model's world with these contents at these positions (and ``older``:
        the supervisor's older state, its Us and each position's session part)."""
        xs = [self.objects(c, p + 1) for p, c in enumerate(nodes)]
        started, lost, dup, power, timed, nv, old, forged, replayed, sup_old, resynced = counted
        sup_older = None
        if older is not None:
            named = self.parts.named
            sessions = tuple(named(x, p + 1) for p, x in enumerate(older[1]))
            sup_older = SupervisorState(self.total, older[0], 0, sessions)
        return World(
            SupervisorState(self.total, usable, 0, tuple(x.session for x in xs)),
            tuple(x.client for x in xs),
            frozenset(item for x in xs for item in x.flight),
            started=started,
            lost=lost,
            duplicated=dup,
            power_lost=power,
            timed_out=timed,
            nv_lost=nv,
            old_copied=old,
            older=tuple(cast(ClientState, x.older) for x in xs) if self.bounds.old_copies else (),
            lost_records=tuple((p + 1, x.ghost) for p, x in enumerate(xs) if x.ghost is not None),
            forged=forged,
            replayed=replayed,
            seen=frozenset(m for x in xs for m in x.seen),
            sup_older=sup_older,
            sup_old_copied=sup_old,
            resynced=resynced,
        )

    # -- listing moves -----------------------------------------------------------------
    def moves_of(self, c: int, p: int) -> NodeMoves:
        """The moves of content ``c`` at position ``p``, listed on first use."""
        nm = self.moves[p][c]
        if nm is None:
            nm = self.moves[p][c] = self._list(c, p)
        return nm

    def _list(self, c: int, p: int) -> NodeMoves:
        x = self.contents[c]

        def moves(specs: list[Spec]) -> list[Move]:
            return [[None, spec[1], p, c, spec] for spec in specs]

        def keyed(specs: list[Spec]) -> list[Keyed]:
            return [(spec[0], i, [None, spec[1], p, c, spec]) for i, spec in enumerate(specs)]

        n, b = p + 1, self.bounds
        nm = NodeMoves(moves(self._listed(("restart", n), self._restart_steps)))
        nm.session = moves(self._listed(("session", x.session, n), self._session_steps))
        nm.flight = keyed(self._listed(("flight", x.flight, n), self._flight_steps))
        nm.client = moves(self._listed(("client", x.client, x.older, n), self._client_steps))
        if b.forgeries:
            nm.forge = moves(self._listed(("forge", x.session, x.client, n), self._forge_steps))
        if x.seen != self.parts.empty_seen:
            nm.replay = keyed(self._listed(("replay", x.seen, n), self._replay_steps))
        nm.flight_moves = [mv for _, _, mv in nm.flight]
        nm.attacks = bool(nm.forge or nm.replay)
        return nm

    def _listed(self, what: tuple[Any, ...], steps: Callable[..., list[Listed]]) -> list[Spec]:
        """``steps(*what[1:])``, each with its guard and what applying it needs; memoized. The
        steps of one part depend on that part and the node id alone."""
        out = self._specs.get(what)
        if out is None:
            out = self._specs[what] = [self._spec(*step) for step in steps(*what[1:])]
        return out

    def _spec(self, key: tuple[int, str], kind: StepKind, arg: int) -> Spec:
        event: Event | Resync | int | None = None
        side = CHANNEL
        if kind is K.DELIVER or kind in ATTACKER_KINDS:
            event = arg
            side = CLIENT if self.parts.to_client(arg) else SESSION
        elif kind is K.SUPERVISOR_POWER_LOSS:
            event, side = (PowerLoss(arg) if arg else POWER_LOSS), SESSION
        elif kind is K.NV_OLD_COPY:
            event, side = PowerLoss(arg), CLIENT
        elif kind is K.NV_BACKUP:  # nothing is fed to a node: ``_apply`` copies the record
            event, side = None, CHANNEL
        elif kind not in CHANNEL_KINDS:
            event = self.model.event(Step(kind, units=arg, commit=bool(arg), nonce=arg))
            side = SESSION if kind in SUPERVISOR_KINDS else CLIENT
        return (key, self.guards.of(kind, arg), kind, arg, self.charge[kind], event, side)

    def _restart_steps(self, n: int) -> list[Listed]:
        """A supervisor power loss, one per SYNC nonce it may draw (the n-th start's)."""
        starts = range(self.bounds.power_losses)
        nonces = [supervisor_nonce(K.SUPERVISOR_POWER_LOSS, p + 1, 0) for p in starts] or [0]
        return [(NO_KEY, K.SUPERVISOR_POWER_LOSS, nonce) for nonce in nonces]

    # As ``Model.steps`` lists them, for any run counters (``Guards`` checks those per world):
    def _session_steps(self, session: int, n: int) -> list[Listed]:
        s = self.parts.named(session, n)
        out: list[Listed] = []
        if s.phase is Phase.IDLE:
            out += [(NO_KEY, K.BEGIN, units) for units in range(1, self.bounds.units + 1)]
        if s.phase is Phase.ACKED:
            out += [(NO_KEY, K.DECIDE, 1), (NO_KEY, K.DECIDE, 0)]
        if s.deadline is not None:
            out.append((NO_KEY, K.SUPERVISOR_TIMER, 0))
        if s.phase is Phase.IDLE and self.model.variant.lifts_tx:
            resyncs = range(RESYNC_NONCE + 1, RESYNC_NONCE + self.bounds.resyncs + 1)
            out += [(NO_KEY, K.RESYNC, nonce) for nonce in resyncs]
        return out

    def _flight_steps(self, flight: int, n: int) -> list[Listed]:
        keyed = sorted((self._key(frame, n), frame) for frame, _ in self.parts.flights[flight])
        kinds = (K.DELIVER, K.LOSE, K.DUPLICATE)
        return [(key, kind, frame) for key, frame in keyed for kind in kinds]

    def _client_steps(self, client: int, older: int, n: int) -> list[Listed]:
        b, c = self.bounds, self.parts.named(client, n)
        out: list[Listed] = []
        if c.deadline is not None:
            out.append((NO_KEY, K.COMMAND_TIMER, 0))
        if c.return_deadline is not None:
            out.append((NO_KEY, K.RETURN_TIMER, 0))
        if b.spending and c.usable >= UNIT and self.model.variant.client.can_spend(c):
            out.append((NO_KEY, K.SPEND, 0))
        if b.returns and c.usable >= UNIT and self.model.variant.client.can_give_back(c):
            out.append((NO_KEY, K.GIVE_BACK, 0))
        restarts = range(RESTART_NONCE + 1, RESTART_NONCE + b.power_losses + 1)
        out += [(NO_KEY, K.CLIENT_POWER_LOSS, nonce) for nonce in restarts]
        out += [(NO_KEY, K.NV_LOST, nonce) for nonce in range(1, b.nv_losses + 1)]
        if b.old_copies and older != client:
            copies = range(OLD_COPY_NONCE + 1, OLD_COPY_NONCE + b.old_copies + 1)
            out += [(NO_KEY, K.NV_OLD_COPY, nonce) for nonce in copies]
            if b.backups:
                out.append((NO_KEY, K.NV_BACKUP, 0))
        return out

    def _forge_steps(self, session: int, client: int, n: int) -> list[Listed]:
        s, c, part = self.parts.named(session, n), self.parts.named(client, n), self.parts.part
        forged = forgeable(self.model.variant, (s,), (c,), self.bounds.units)
        return [(NO_KEY, K.FORGE, part(msg)) for msg in forged]

    def _replay_steps(self, seen: int, n: int) -> list[Listed]:
        keyed = sorted((self._key(frame, n), frame) for frame in self.parts.seens[seen])
        return [(key, K.REPLAY, frame) for key, frame in keyed]

    def _key(self, frame: int, n: int) -> tuple[int, str]:
        return message_key(self.parts.named(frame, n))

    # -- the supervisor's state file (its old copies) ---------------------------------------
    def wrote(self, before: int, after: int, credit: int) -> bool:
        """A step from content ``before`` to ``after`` wrote the supervisor's state file: its
        session's record changed or Us moved (``Model._to_session``)."""
        if credit:
            return True
        a, b = self.contents[before].session, self.contents[after].session
        if a == b:
            return False
        key = (a, b)
        out = self._wrote.get(key)
        if out is None:
            persistent, objects = self.model.variant.supervisor.persistent, self.parts.objects
            out = self._wrote[key] = persistent(objects[a]) != persistent(objects[b])
        return out

    def restored(self, c: int, p: int, session: int, nonce: int) -> Result:
        """Content ``c`` at position ``p`` with its session put back to part ``session`` and
        restarted with SYNC nonce ``nonce`` (the supervisor's old copy comes back)."""
        key = (c, p, session, nonce)
        out = self._restored.get(key)
        if out is None:
            back = self.intern(self.contents[c]._replace(session=session))
            spec = self._spec(NO_KEY, K.SUPERVISOR_POWER_LOSS, nonce)
            r = self._apply(back, p + 1, spec)
            out = self._restored[key] = (r[0], r[1], 0, self.frames[r[0]] - self.frames[c])
            if r[0] < 0:
                out = INVALID
        return out

    # -- applying moves ----------------------------------------------------------------
    def resolve(self, mv: Move) -> Result:
        """The move's result, worked out (as ``Model.apply`` does) on first use."""
        if mv[RESULT] is None:
            mv[RESULT] = self._apply(mv[CONTENT], mv[POS] + 1, mv[SPEC])
        result: Result = mv[RESULT]
        return result

    def _apply(self, c: int, n: int, spec: Spec) -> Result:
        """``Model._apply`` on content ``c`` as node ``n``: the channel's part of the step, then
        the event fed to the session (``_to_session``) or the client (``_to_client``), then the
        frames it sends (``_out``)."""
        _, _, kind, arg, charge, event, side = spec
        parts = self.parts
        session, client, flight, older, ghost, seen = self.contents[c]
        credit = 0
        sent: tuple[int, ...] = ()
        if kind is K.DUPLICATE:
            flight = parts.add(flight, (arg,))
        elif kind is K.DELIVER or kind is K.LOSE:
            flight = parts.remove(flight, arg)
        elif kind is K.FORGE and self.bounds.replays:  # a forged frame can be replayed too
            seen = parts.seen_with(seen, (arg,))
        elif kind is K.NV_LOST:
            record = parts.objects[client]
            before = ghost or NOT_LOST
            ghost = LostRecord(max(record.credited, before.credited), record.spent + before.spent)
        elif kind is K.NV_BACKUP:  # a copy of the record as it is now
            older = client
        elif kind is K.NV_OLD_COPY:  # the old record comes back; the node restarts from it
            objects = parts.objects
            ghost = restored_ghost(ghost or NOT_LOST, objects[client], objects[older])
            client = older
        assert event is not None or side == CHANNEL
        if side == SESSION:
            try:
                session, credit, sent = parts.session_step(session, n, event)  # type: ignore[arg-type]
            except LocalProtocolError:  # a BEGIN the rules refuse (``Model.apply``)
                if kind is not K.BEGIN:
                    raise
                return INVALID
        elif side == CLIENT:
            old = client
            client, sent, persisted = parts.client_step(old, n, event)  # type: ignore[arg-type]
            if older >= 0 and persisted and not self.bounds.backups:
                older = old
        if sent:
            flight = parts.add(flight, sent)
            if self.bounds.replays:
                seen = parts.seen_with(seen, sent)
        if parts.objects[session].tx > self.tx_limit:
            return INVALID
        new = self.intern(Content(session, client, flight, older, ghost, seen))
        return (new, credit, charge, self.frames[new] - self.frames[c])


class _Objects(NamedTuple):
    session: Any
    client: Any
    flight: list[tuple[Any, int]]
    older: Any
    ghost: LostRecord | None
    seen: list[Any]
