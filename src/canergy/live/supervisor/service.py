"""The supervisor service: the sans-IO core plus grant policy, safety limits, files and status.

It implements the bus loop's ``Handler``: frames and deadlines in, frames out. Every change of
the core's persistent record is written to the state file *before* the frames it causes are
sent, so a ``kill -9`` at any point restarts from books that never owe energy.
"""

from __future__ import annotations

import logging
import secrets
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, TextIO, cast

import can

from canergy.auth.frames import FrameAuth, Verdict
from canergy.codec import DecodeError
from canergy.core import (
    Acknowledged,
    Action,
    Admitted,
    AheadOfImage,
    Persist,
    Resolved,
    ReturnCredited,
    Send,
)
from canergy.core.common import at_end
from canergy.core.errors import LocalProtocolError, WindowClosed
from canergy.core.state import SYNC_PHASES, Outcome
from canergy.core.supervisor import BUS_SHIFT, SupervisorCore
from canergy.core.witnessed import answered, counts_taken
from canergy.live.runtime import BusCounters, FramePath, Outgoing, RawFrame
from canergy.live.supervisor.evidence import beyond_books, impossible
from canergy.live.supervisor.frame_path import (
    ANSWERED,
    HELD,
    JOIN_HELD,
    TELEMETRY,
    CoreFramePath,
    FastFrame,
    Pass,
)
from canergy.live.supervisor.grants import Books, GrantCallback, GrantDesk, GrantRequest
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.joins import JOIN_HOLD_US
from canergy.live.supervisor.ledger import Ledger
from canergy.live.supervisor.nodes import NodeInfo, name_of
from canergy.live.supervisor.outputs import StatusOut
from canergy.live.supervisor.policy import Limits, TopUp
from canergy.live.supervisor.rules_said import RulesSaid
from canergy.live.supervisor.status import Run, StatusReport
from canergy.live.supervisor.stopping import Stopping
from canergy.live.supervisor.telemetry import BEYOND_BOOKS, TelemetryTable
from canergy.live.supervisor.watch import BusWatch
from canergy.live.supervisor.witness import RETURN_HOLD_MIN_US
from canergy.messages import (
    SEQ_BITS,
    Debit,
    Join,
    Message,
    Return,
    Telemetry,
    ToSupervisor,
)
from canergy.seqnum import unwrap
from canergy.units import format_energy

log = logging.getLogger(__name__)

RESYNC_GAP_US = 1_000_000
"""Witnessed rules: a node whose counts are ignored is re-synced at most once in this long (a
node left answering re-sends them every retry period; a replayed counts frame, which verifies
for its key epoch, costs the node at most one re-sync a second)."""


@dataclass(frozen=True, slots=True)
class ServiceConfig:
    policy: TopUp | None = None
    limits: Limits = field(default_factory=Limits)
    state_path: Path | None = None
    status_path: Path | None = None
    status_stream: TextIO | None = None
    status_text: Callable[[dict[str, Any]], str] | None = None
    """How a status reads on ``status_stream``: None, JSON (one object a line); else the line
    this makes of it (``canergy supervisor --listen-only``). The status file is always JSON."""
    status_period_us: int = 1_000_000
    lost_after_us: int = 3_000_000
    tick_us: int = 50_000
    stop_timeout_us: int = 5_000_000
    listen_only: bool = False
    fsync: bool = True
    inject_uj: int = 0
    """Energy added to Us (counted as injected) once, at start, and saved before any grant."""
    stop_on_intrusion: bool = False
    """Evidence of an intrusion: stop (grant nothing more, settle, exit non-zero) instead of
    only counting and reporting it. Without a key: a frame only this supervisor may send, from
    someone else. In authenticated mode only authentic evidence (``authentic_intrusion``): frames
    without a MAC, with a bad one or a stale one are refused and counted, never a reason."""
    return_hold_us: int | None = None
    """Without a key: hold each RETURN until the node's own TELEMETRY confirms it and this long
    has passed without the node reporting frames in its name (``canergy.live.supervisor.witness``),
    at least ``RETURN_HOLD_MIN_US`` (less is a ``ValueError``: the node could not refute a forged
    one in time); None: credit at once (authenticated mode, where a RETURN carries a MAC)."""
    witness_block_us: int = 10_000_000
    """No top-ups for a node this long after evidence against its TELEMETRY."""
    join_hold_us: int = JOIN_HOLD_US
    """A JOIN confirmed by the node's TELEMETRY without books is admitted this long after it: a
    node that is on and has its books sees a JOIN or a TELEMETRY in its name that it did not
    send (forged without a key, replayed from an earlier life with one) and reports at once,
    with its books, which drops the JOIN before anything is written off. 0: admitted on the
    confirming TELEMETRY."""
    local_nodes: frozenset[int] = frozenset()
    """Nodes only this process speaks for (the proxies of guarded CiA 402 drives: a frame on the
    bus in their name never reaches the core): a JOIN of theirs needs no hold."""
    bus_names: tuple[str, ...] = ()
    """Several buses (``canergy supervisor --bus``): their names in order. The core's session
    keys are then ``bus index << 8 | node``, shown and saved as ``bus/node``."""

    def __post_init__(self) -> None:
        hold = self.return_hold_us
        if hold is not None and hold < RETURN_HOLD_MIN_US:
            raise ValueError(
                f"return_hold_us {hold} is less than {RETURN_HOLD_MIN_US}: the node could not "
                "refute a forged RETURN in time"
            )


@dataclass(frozen=True, slots=True)
class ServiceParts:
    """The service's parts, made by the builder (``canergy.live.supervisor.build.service_parts``;
    the core's own in C where it has them). None calls back into the service: they share the
    loop pass (``passes``) and the stop (``stopping``) with it, and return what the service is
    to do."""

    heard: TelemetryTable
    """The TELEMETRY table (``telemetry.HeardTable``, or the compiled core's in C)."""
    nodes: dict[int, NodeInfo]
    rules_said: RulesSaid
    desk: GrantDesk
    ledger: Ledger
    status_out: StatusOut
    intrusions: Intrusions
    refusals: Refusals
    witness: Any
    """The witness (``witness.ReturnGate``, or the compiled core's in C)."""
    joins: Any
    """The held JOINs (``joins.JoinHold``, or the compiled core's in C)."""
    bus_counters: BusCounters
    buses: dict[str, BusCounters]
    passes: Pass
    """The bus loop's passes: frames held until the outermost one ends."""
    stopping: Stopping
    watch: BusWatch
    """Refusals and intrusions, and the stop they may ask for."""
    path: CoreFramePath
    """The core's frame path (``frame_path``), the compiled core's or the Python core's."""
    report: StatusReport
    """Makes the status from the parts it reads (``status``)."""
    is_lost: Callable[[int, int], bool]
    """``nodes.lost`` for these nodes, the liveness test and ``lost_after_us``."""


class SupervisorService:
    """Grants energy to nodes on one bus; implements ``canergy.live.runtime.Handler``. Over
    several buses, ``canergy.live.supervisor.multi_bus`` puts one port per bus in front of it."""

    def __init__(
        self,
        core: SupervisorCore,
        config: ServiceConfig,
        now: int,
        parts: ServiceParts,
        *,
        liveness: Callable[[int, int], bool] | None = None,
    ) -> None:
        """Made by the builder (``canergy.live.supervisor.build``), which hands over ``parts``
        and ``liveness``, an extra liveness test (the CANopen heartbeat watchdog, the guarded
        drives'; False: no grants)."""
        self.core = core
        self.config = config
        self.heard = parts.heard
        self.nodes = parts.nodes
        self.rules_said = parts.rules_said
        """Which rules each node's TELEMETRY says (``rules_said``): other than these, no grant."""
        self.desk = parts.desk
        """Sizes one-shot grants and top-ups under the limits and the rate limiter."""
        self.started_at = now
        self.now = now
        self.next_status = now
        self.next_tick = now
        self.ready: set[int] = set()
        """Nodes to try a grant for at the loop's next pass (a request queued, a transaction
        ended); every node is tried at each tick."""
        self.ended: set[int] = set()
        """Nodes at the end of their numbering (``COUNTER_END``): granted nothing more."""
        self._stopping = parts.stopping
        """Set by ``stop`` or by the watch on evidence; shared with the frame path."""
        self._pass = parts.passes
        """The bus loop's passes: frames held until the outermost one ends."""
        self.telemetry_heard = 0
        """TELEMETRY frames of managed nodes taken (information, not protocol frames)."""
        self.ledger = parts.ledger
        """The books of this run: granted since the start, an injection, their writing."""
        self.status_out = parts.status_out
        self.liveness = liveness
        self.bus_counters = parts.bus_counters
        self.buses = parts.buses
        """Several buses: each one's counters by name (the status shows them and their sums)."""
        self.intrusions = parts.intrusions
        self.refusals = parts.refusals
        """Authenticated mode: frames refused by the MAC or freshness check, with rates."""
        self.watch = parts.watch
        self.witness = parts.witness
        self.witnessed = core.variant.name == "witnessed"
        """Rules that take DEBIT (``witnessed``): draws held, every node start confirmed. Every
        table has a cell for DEBIT (tables are total); the others ignore it, and so does this."""
        self._resuming: int | None = None
        """The node whose RESUME the core is answering (its admission is no JOIN's)."""
        self.joins = parts.joins
        """JOINs held until the node's TELEMETRY confirms or refutes them (evidence)."""
        self.path = parts.path
        self.report = parts.report
        self.is_lost = parts.is_lost
        self.ledger.open(config.inject_uj)  # an injection is on disk before anything is granted
        self._waited = self.waiting()
        """The nodes this start waited for at the last look (witnessed rules; only the counts
        answering a SYNC, ``_synced``, shrink it, and nothing after the start grows it: empty,
        no pass looks at every session)."""
        if self._waited:
            log.warning("%s", self.waiting_why(self._waited))
        self.started_without = self._started_without()
        """This start's nodes not waited for (``start_without``) and what their books said
        each held (µJ, by name): written off, out of the budget unless they answer with books."""
        if self.started_without:
            log.warning("%s", self.started_without_why())

    @property
    def stopping(self) -> bool:
        """No more transactions begin (``stop``, or evidence under ``--on-intrusion stop``)."""
        return self._stopping.asked

    @property
    def stop_deadline(self) -> int | None:
        """When the stop writes off what is still open (``finished``)."""
        since = self._stopping.since
        return None if since is None else since + self.config.stop_timeout_us

    # -- Handler ---------------------------------------------------------------------------
    def on_message(self, msg: Message, now: int) -> Sequence[Message]:
        self.now = now
        info = self.nodes.get(msg.node)
        if info is None:
            return ()
        if isinstance(msg, Telemetry):
            s = self.core.session(msg.node)
            verdict = self.heard.telemetry(msg.node, s, msg.level_mj, msg.flags, now)
            return self._flush(self._telemetry(msg, verdict, now))
        # listen-only keeps no books of its own (another supervisor may be granting): no
        # judgement by them, or every answer would look impossible
        if self.config.listen_only or not isinstance(msg, ToSupervisor):
            info.heard.heard_at = now
            return ()
        if (impossible := self._impossible(msg)) is not None:
            self.watch.intrusion(msg.node, repr(msg), impossible, now)
            return ()  # moves nothing: no honest node sends it
        info.heard.heard_at = now
        if isinstance(msg, Join):  # a replay or forgery looks the same: the node's report tells
            self.joins.on_join(msg)
            return ()
        if isinstance(msg, Return) and self._hold_return(msg, now):
            return self._flush(self._released(msg.node, now))
        if isinstance(msg, Debit) and msg.flags & (Debit.SYNC | Debit.BOOKS) and self.witnessed:
            out = self._synced(msg, info, now)
        elif isinstance(msg, Debit) and msg.is_resume and self.witnessed:
            if self._hold_resume(msg, now):
                return self._flush(self._released(msg.node, now))
            out = self._resume(msg, info, now)
        else:
            out = self._carry_out(self.core.receive(msg, now), now)
        if self.ready:  # a transaction ended: the node's next grant goes out in this step
            out += self._start_grants(now, self.ready)
        return self._flush(out)

    def _telemetry(
        self, msg: Telemetry, verdict: int, now: int, found: int | None = None
    ) -> list[Outgoing]:
        """A TELEMETRY the table took (``verdict``, its bits): the evidence it carries, RETURNs
        and JOINs it confirms, and the grants it lets begin. ``found``: what the witness in C
        found in it already (the frame path), else the witness takes it here."""
        self.now = now
        self.telemetry_heard += 1
        self.rules_said.telemetry(msg)
        # listen-only keeps no books of its own (another supervisor may be granting): no
        # judgement by them, or every level reported would look impossible
        if verdict & BEYOND_BOOKS and not self.config.listen_only:
            why = beyond_books(msg.level_mj, self.core.session(msg.node))
            self.watch.intrusion(msg.node, repr(msg), why, now)
        evidence, notes = (
            self.witness.telemetry(msg, self.core.session(msg.node).returns_credited, now)
            if found is None
            else self.witness.telemetry_words(msg, self._credited(msg.node), found & 0xFF)
        )
        for line in evidence:
            self.watch.intrusion(msg.node, repr(msg), line, now, stop=True)
        for line in notes:
            log.warning("node %s: %s", self.node_name(msg.node), line)
        self.ready.add(msg.node)
        out = self._released(msg.node, now)  # grown in place: no list made per step
        admit = (
            self.joins.on_telemetry(msg, now)
            if found is None
            else self.joins.telemetry_taken(msg, now, found >> 8)
        )
        if admit:
            out += self._admit(admit, now)
        out += self._start_grants(now, self.ready)
        return out

    def _admit(self, joins: list[Join], now: int) -> list[Outgoing]:
        """The JOINs the held JOINs confirmed (``joins``), answered by the core."""
        out: list[Outgoing] = []
        for join in joins:
            out += self._carry_out(self.core.receive(join, now), now)
        return out

    def _credited(self, node: int) -> Callable[[], int]:
        """The number of ``node``'s last debit credited, read when asked for."""
        return lambda: self.core.session(node).returns_credited

    def _distrusted(self, node: int, now: int) -> bool:
        """Without a key: no top-ups while the node's TELEMETRY was lately contradicted (with a
        key, anyone could make the node count frames in its name: that is no reason)."""
        return not self.watch.authenticated and self.witness.blocked(node, now)

    def _hold_return(self, msg: Return, now: int) -> bool:
        """Detection mode: a fresh RETURN waits for the node's confirmation (``witness``)."""
        credited = self.core.session(msg.node).returns_credited
        if self.config.return_hold_us is None or self.witness.old(msg, credited):
            return False
        if (evidence := self.witness.hold(msg, credited, now)) is not None:
            self.watch.intrusion(msg.node, repr(msg), evidence, now, stop=True)
        return True

    def _held_in_c(self, msg: Return, verdict: int, now: int) -> list[Outgoing]:
        """A RETURN the witness in C held on the frame path (``verdict``: the witness's): as
        ``_hold_return`` and what follows it on the usual path."""
        self.now = now
        self.nodes[msg.node].heard.heard_at = now
        credited = self.core.session(msg.node).returns_credited
        if (evidence := self.witness.hold_words(msg, credited, verdict)) is not None:
            self.watch.intrusion(msg.node, repr(msg), evidence, now, stop=True)
        return self._released(msg.node, now)

    def _hold_resume(self, msg: Debit, now: int) -> bool:
        """A RESUME (witnessed rules): without a key, one whose pending return the core would
        credit waits for the node's TELEMETRY, as a RETURN does (``witness``)."""
        credited = self.core.session(msg.node).returns_credited
        waiting = self.witness.resume_held(msg.node)
        if not self.witness.hold_resume(msg, credited, now, self.config.return_hold_us is not None):
            return False
        if not waiting:
            log.warning(
                "node %s: RESUME with a pending return of %d mJ held until its TELEMETRY "
                "confirms it (no key); nothing granted meanwhile",
                self.node_name(msg.node),
                msg.amount_mj,
            )
        return True

    def _resume(self, msg: Debit, info: NodeInfo, now: int) -> list[Outgoing]:
        """A node's start with books, answered by the core (ADMIT): confirmed, or found behind
        (its last debit below the books': an older record) and admitted afresh."""
        s = self.core.session(msg.node)
        seq = unwrap(msg.seq, s.returns_credited, SEQ_BITS)
        repeat = answered(s, msg.nonce, seq)  # answered as before: no news
        self._resuming = msg.node
        try:
            out = self._carry_out(self.core.receive(msg, now), now)
        finally:
            self._resuming = None
        if repeat:
            return out
        info.resumes += 1
        info.ended_at = now  # its level before the answer is stale
        name = self.node_name(msg.node)
        if seq < s.returns_credited:
            info.found_behind += 1
            log.warning(
                "node %s started from a record older than the books (its last debit %d, the "
                "books hold %d): admitted afresh at tx %d; what that record held is dropped",
                name,
                seq,
                s.returns_credited,
                self.core.session(msg.node).tx,
            )
        else:
            log.info("node %s resumed: its books confirmed at debit %d", name, seq)
        return out

    def waiting(self) -> tuple[int, ...]:
        """The nodes whose books this start waits for before any grant (the core's
        ``unconfirmed``; none under rules without SYNC)."""
        return tuple(self.core.unconfirmed())

    def waiting_why(self, waiting: tuple[int, ...]) -> str:
        """Why nothing is granted while ``waiting`` (``waiting()``) is not empty."""
        names = ", ".join(str(self.node_name(n)) for n in waiting)
        return (
            f"started from the state file: SYNC sent; no grant to any node until node(s) "
            f"{names} answer with their books (the file may be an older copy: granting before "
            "would grant again what they hold); --start-without NODES skips a node, at a risk"
        )

    def _started_without(self) -> dict[str, int]:
        """The nodes a start skips (the core's ``start_without``) that it would wait for, and
        what each one's books say it holds: delivered and reserved, less returns credited."""
        skipped = self.core.start_without
        return {
            str(self.node_name(s.node)): s.delivered + s.reserved - s.returned
            for s in self.core.state.sessions
            if s.node in skipped and s.phase in SYNC_PHASES
        }

    def started_without_why(self) -> str:
        """What ``started_without`` means, one line."""
        held = self.started_without
        each = ", ".join(f"node {name} {uj / 1e6:.3f} J" for name, uj in held.items())
        return (
            f"started without node(s) {', '.join(held)} (--start-without): not waited for; "
            f"written off what their books say they hold, {sum(held.values()) / 1e6:.3f} J "
            f"({each}); if the state file is an older copy they may hold more, which the "
            "budget counts again"
        )

    def _synced(self, msg: Debit, info: NodeInfo, now: int) -> list[Outgoing]:
        """The books or counts answering this start's SYNC: the core takes them; once the
        counts are taken the node is confirmed, and once every node is, grants resume."""
        s = self.core.session(msg.node)
        outside = msg.is_counts and s.phase not in SYNC_PHASES
        if outside and not counts_taken(self.core.timing, s, msg):  # an earlier start's
            info.counts_ignored += 1  # the rules ignore it; the witness's baseline stays
            out = self._carry_out(self.core.receive(msg, now), now)
            if (last := info.resynced_at) is not None and now - last < RESYNC_GAP_US:
                return out
            return out + self._resync(msg.node, "its counts were ignored", now)
        other = s.phase in SYNC_PHASES and msg.nonce != s.sync_nonce  # ignored: not this start's
        if msg.is_counts and not other:  # the node's return numbers start again, as at a RESUME
            self.witness.hold_resume(msg, s.returns_credited, now, False)
        out = self._carry_out(self.core.receive(msg, now), now)
        if s.resync and self.core.idle(msg.node) and info.requests:
            self.ready.add(msg.node)  # a re-sync ended: the grant that waited for it is tried
        waiting = self.waiting()
        if msg.node in self._waited and msg.node not in waiting:
            info.synced += 1
            info.ended_at = now  # its level before the answer is stale
            log.warning(
                "node %s confirmed its books after this start (tx %d, debit %d)",
                self.node_name(msg.node),
                self.core.session(msg.node).tx,
                self.core.session(msg.node).returns_credited,
            )
            if not waiting:
                log.warning("every node has confirmed its books: granting")
                self.ready.update(n for n, i in self.nodes.items() if i.requests)  # they waited
        self._waited = waiting
        return out

    def _released(self, node: int, now: int) -> list[Outgoing]:
        """The held RETURNs of ``node`` its TELEMETRY has confirmed, credited by the core (and a
        held RESUME it confirmed, answered)."""
        out: list[Outgoing] = []
        if not self.witness.holds(node):
            return out
        credited = self.core.session(node).returns_credited
        for ret in self.witness.release(node, credited, now):
            if isinstance(ret, Debit):
                out += self._resume(ret, self.nodes[node], now)
                continue
            if ret.amount_mj == 0:
                kind = "return numbers acknowledged by someone else: resynchronised at 0 mJ"
                self.watch.intrusion(node, repr(ret), kind, now, stop=True)
            out += self._carry_out(self.core.receive(ret, now), now)
        return out

    def _impossible(self, msg: Message) -> str | None:
        """What no honest node sends (``evidence.impossible``; a level: the TELEMETRY table's
        verdict)."""
        return impossible(msg, self.core.session(msg.node))

    def on_decode_error(
        self, error: DecodeError, frame: can.Message, node: int | None = None
    ) -> None:
        """``node``: the session key of the frame's node (default: its node id)."""
        self.watch.decode_error(frame, node)

    def on_foreign_direction(
        self, frame: can.Message, now: int, node: int | None = None
    ) -> Sequence[Message]:
        """A frame only this supervisor sends, from someone else (``BusWatch.foreign_direction``;
        ``node`` as in ``on_decode_error``)."""
        self.watch.foreign_direction(frame, now, node)
        return ()

    def on_auth_failure(self, verdict: Verdict, frame: can.Message, now: int) -> None:
        """A refused frame: counted and reported, never acted on (``BusWatch.auth_failure``)."""
        self.watch.auth_failure(verdict, frame, now)

    @property
    def freshness(self) -> Callable[[Message], int | None]:
        """Authenticated mode: the freshness value of a frame to or from ``msg.node``
        (``BusWatch.freshness``; the bus loop calls it per frame: no call of the service's)."""
        return self.watch.freshness

    @property
    def authenticated(self) -> bool:
        """Whether the bus loop checks MACs (``--auth``): it marks the counters it shares."""
        return self.watch.authenticated

    @property
    def stopped_by_intrusion(self) -> bool:
        """Whether evidence stopped the supervisor (``--on-intrusion stop``)."""
        return self.watch.stopped_by_intrusion

    def node_name(self, node: int) -> int | str:
        """A node as status, replies and the state file name it: its id, or ``bus/node``."""
        return name_of(self.config.bus_names, node)

    def intrusion(self, node: int, what: str, kind: str, now: int, *, stop: bool = False) -> None:
        """Report what no honest participant sends (``BusWatch.intrusion``)."""
        self.watch.intrusion(node, what, kind, now, stop=stop)

    def authentic_intrusion(self, node: int, what: str, kind: str, now: int) -> None:
        """Authentic evidence of intrusion: what only a holder of a key could have sent, checked
        under that key; ``--on-intrusion stop`` acts on it (``BusWatch.authentic_intrusion``)."""
        self.watch.authentic_intrusion(node, what, kind, now)

    def next_wakeup(self) -> int | None:
        wakeup = self.next_status  # the earliest of these (compared, no min(): every pass)
        if self.next_tick < wakeup:
            wakeup = self.next_tick
        if self.ready and not self.stopping and self.now < wakeup:
            wakeup = self.now
        if (release := self.witness.next_release()) is not None and release < wakeup:
            wakeup = release
        if (admission := self.joins.next_wakeup()) is not None and admission < wakeup:
            wakeup = admission
        timer = self.core.get_timer()
        return wakeup if timer is None or wakeup <= timer else timer

    def on_wakeup(self, now: int) -> Sequence[Message]:
        self.now = now
        out: list[Outgoing] = []
        if not self.config.listen_only:
            timer = self.core.get_timer()
            if timer is not None and timer <= now:
                out += self._carry_out(self.core.handle_timer(now), now)
            for node in self.witness.holding():
                out += self._released(node, now)
            out += self._admit(self.joins.on_wakeup(now), now)
            out += self._start_grants(now, None if now >= self.next_tick else self.ready)
        if now >= self.next_tick:
            self.next_tick = now + self.config.tick_us
        if now >= self.next_status:
            self.write_status()
            self.next_status = now + self.config.status_period_us
        self.refusals.tick(now)  # what was refused since the last line, once a second at most
        return self._flush(out)

    def frame_path(
        self, off: str | None = None, auth: FrameAuth | None = None, bus: int = 0
    ) -> FramePath | None:
        """The frame path for this service's bus loop (``BusRuntime(frame_path=)``, from the
        builder): the core's (``CoreFramePath.fast_frame``, what it took recorded here,
        ``_took``), or None where every frame takes the usual path: ``off``, why the core's
        cannot run here (listen-only), or the Python core with a key. From then on, in a loop
        pass, frames the core encoded (COMMIT, ABORT; the C core's INTENTION too) go to the
        loop as its bytes (``RawFrame``), never decoded and encoded again. The status says
        which path runs (``frame_path``), why not the core's (``frame_path_off``) and how many
        frames it took (``frame_path_frames``).

        ``auth``: the bus loop's key: the compiled core then verifies and protects in C
        (``fast_auth_frame``; classic layout: ``fast_auth_pair``), and an INTENTION it begins
        in a loop pass is protected in C too.

        ``bus``: over several buses, the index of the bus whose loop asks (each asks with the
        same ``off`` and, with a key, its own ``FrameAuth`` in the same layout): that bus's
        frames go to its own supervisor in C, verified under the keys that bus's ``FrameAuth``
        gives. An INTENTION is protected in C once every bus's loop has asked."""
        fast = self.path.frame_path(off, auth, bus)
        return None if fast is None else partial(self._took, fast)

    def _took(self, fast: FastFrame, frame: can.Message, now: int) -> bool:
        """A frame through the core's path (``fast``): what the core took of it recorded
        here, in the loop pass; False, nothing done, for the loop's usual path."""
        taken = fast(frame, now)
        if taken is None:
            return False
        what, node, payload, verdict = taken
        if what == ANSWERED:  # its frames are held already: what the books record follows
            self._pass.held += self._answered(node, payload, now)
        elif what == TELEMETRY:  # what the table and the witness in C found in it
            self._pass.held += self._telemetry(payload, verdict & 0xFF, now, verdict >> 8)
        elif what == HELD:  # a RETURN the witness in C held
            self._pass.held += self._held_in_c(payload, verdict, now)
        elif what == JOIN_HELD:
            self._join_held(node, now)
        else:  # DECODED: a RETURN, JOIN or DEBIT, as if the loop had decoded it
            self.on_message(payload, now)  # in a pass: its frames are held
        return True

    @property
    def frames_in_c(self) -> int:
        """Frames the compiled core's frame path took (``CoreFramePath.frames``; 0 on the
        Python core, whose path counts its own in the status)."""
        return self.path.frames if self.path.core == "c" else 0

    def _answered(self, node: int, actions: list[Action], now: int) -> list[Outgoing]:
        """An answer the core's path took (its frames already held): what the books record
        and the node's next grant (a transaction ended)."""
        self.now = now
        self.nodes[node].heard.heard_at = now
        out = self._carry_out(actions, now)
        if self.ready:  # a transaction ended: the node's next grant goes out in this pass
            out += self._start_grants(now, self.ready)
        return out

    def _join_held(self, node: int, now: int) -> None:
        """A JOIN the compiled core's frame path held: the node was heard."""
        self.now = now
        self.nodes[node].heard.heard_at = now

    # -- loop passes -----------------------------------------------------------------------
    def begin_pass(self) -> None:
        """Hold every frame until ``end_pass``: the state file is then written once for the
        whole pass (a drained batch of frames and the deadlines then due) before any of the
        pass's frames leaves. Passes nest (several buses' runtimes open one each)."""
        self._pass.depth += 1

    def end_pass(self) -> list[Outgoing]:
        """Close a pass; the outermost one writes the state file if anything changed and returns
        every frame held since the pass began, in order, for the caller to send."""
        passes = self._pass
        if not passes.depth:
            raise RuntimeError("end_pass without begin_pass")
        passes.depth -= 1
        if passes.depth:
            return []
        held, passes.held = passes.held, []
        self.ledger.save_if_dirty()
        return held

    # -- control ---------------------------------------------------------------------------
    def request_grant(self, node: int, amount: int, reply: GrantCallback) -> None:
        """Queue a one-shot grant; ``reply`` gets the outcome as a JSON-able dict."""
        info = self.nodes.get(node)
        if info is None:
            name = self.node_name(node)
            reply({"node": name, "error": f"node {name} is not managed by this supervisor"})
        elif self.config.listen_only or self.stopping:
            reply({"node": self.node_name(node), "error": "supervisor is listen-only or stopping"})
        else:
            info.requests.append(GrantRequest(node, amount, reply))
            self.ready.add(node)  # start it at the loop's next pass, not a tick later

    def stop(self, now: int) -> None:
        """Start no more transactions; open ones settle or are written off by the rules."""
        self._stopping.ask(now)
        self._refuse_requests()

    def _refuse_requests(self) -> None:
        """Stopping: the one-shot grants still queued are answered with why nothing is granted
        (at the stop, or at the next pass when the watch stopped the supervisor)."""
        for info in self.nodes.values():
            if not info.requests:
                continue
            why = (
                "supervisor stopping"
                if info.heard.heard_at is not None and not info.heard.flags & Telemetry.JOINING
                else "node never heard from (or still joining): nothing granted"
            )
            for req in [*info.requests]:
                req.reply({"node": self.node_name(req.node), "error": why})
            info.requests.clear()

    def finished(self, now: int) -> bool:
        if not self.stopping:
            return False
        assert self.stop_deadline is not None
        return self.core.is_quiescent() or now >= self.stop_deadline

    # -- internals -------------------------------------------------------------------------
    def node_rebooted(self, node: int, now: int) -> None:
        """The node restarted (CANopen boot-up): no grant until it reports its level again.
        An open transaction needs nothing special: the node restarts from its NV record and the
        supervisor's next re-send settles it (the rules were model-checked with power losses)."""
        info = self.nodes.get(node)
        if info is not None:
            info.heard.level = None
            info.ended_at = now

    def _start_grants(self, now: int, nodes: set[int] | None) -> list[Outgoing]:
        """Begin what ``nodes`` (None: every node) may get now; they leave ``ready``."""
        if self.stopping or self.config.listen_only:
            self.ready.clear()
            if self.stopping and nodes is None:  # at each tick: what waited is answered
                self._refuse_requests()
            return []
        todo = list(self.nodes) if nodes is None else sorted(nodes)
        self.ready.clear()
        if self._waited and self.waiting():  # no grant to anyone until every node's books
            return []  # are in: requests wait (the status and stderr say why)
        out: list[Outgoing] = []
        policy = self.config.policy
        for node in todo:
            info = self.nodes[node]
            if not info.requests and policy is None:
                continue  # nothing asked for, no policy: nothing to begin (the cheap test first)
            if not self.core.idle(node):
                continue
            if self.liveness is not None and not self.liveness(node, now):
                continue  # heartbeat lost or not OPERATIONAL: nothing for it, not even one-shots
            if (
                info.heard.heard_at is None
                or info.heard.flags & Telemetry.JOINING
                or self.joins.holding(node)
                or self.witness.resume_held(node)
            ):
                continue  # not heard yet, or no books until admitted: a grant would be lost
            if self.rules_said.other(info.rules):  # ``RulesSaid.mismatched``
                for req in info.requests:
                    req.reply({"node": self.node_name(node), "error": self.rules_said.why(node)})
                info.requests.clear()
                continue  # other rules: one side would spend or wait on what the other lacks
            if info.requests:
                out += self._one_shot(node, info, now)
            elif policy is not None and not self._distrusted(node, now):
                out += self._top_up(node, info, now)
        return out

    def _one_shot(self, node: int, info: NodeInfo, now: int) -> list[Outgoing]:
        req = info.requests.pop(0)
        level = info.heard.level
        amount = self.desk.one_shot(req, self.node_name(node), level, self._books(), now)
        if amount is None:
            return []
        info.active_request = req
        return self._begin(node, amount, now)

    def _top_up(self, node: int, info: NodeInfo, now: int) -> list[Outgoing]:
        heard = info.heard
        level, level_at = heard.level, heard.level_at
        if level is None or level_at is None or level_at <= info.ended_at:
            return []  # no report since the last transaction ended: the level is stale
        if self.is_lost(node, now):
            return []
        amount = self.desk.top_up(level, self._books(), now)
        return self._begin(node, amount, now) if amount else []

    def _books(self) -> Books:
        """What a grant is sized by (what was granted since the start only when a limit
        needs it: the sum runs over every session)."""
        total = self.ledger.granted_total() if self.config.limits.max_total is not None else 0
        return Books(self.core.usable, total)

    def _begin(self, node: int, amount: int, now: int) -> list[Outgoing]:
        encoded = self.path.begin_encoded if self._pass.depth else None
        frames: list[Outgoing] = []
        try:
            if encoded is None:
                actions = self.core.begin(node, amount, now)
            else:
                actions, raw = encoded(node, amount, now)
                bus = node >> BUS_SHIFT  # over several buses: the node's
                frames = [RawFrame(i, d, self.path.begin_fd, bus) for i, d in raw]
        except LocalProtocolError as exc:  # budget changed under us: report, do not crash
            if isinstance(exc, WindowClosed):  # a one-shot grant waits for the re-sync
                self._requeue(node)  # as it waits for a node not heard yet
                return self._resync(node, "its window is used up", now)
            self._finish_request(node, {"node": self.node_name(node), "error": str(exc)})
            if at_end(self.core.session(node).tx) and node not in self.ended:
                self.ended.add(node)
                log.warning("%s", exc)  # once: the top-up policy asks again each pass
            return []
        self.desk.took(amount)
        return frames + self._carry_out(actions, now)

    def _requeue(self, node: int) -> None:
        """The one-shot grant being begun goes back to the head of the node's queue."""
        info = self.nodes[node]
        if info.active_request is not None:
            info.requests.insert(0, info.active_request)
            info.active_request = None

    def _resync(self, node: int, why: str, now: int) -> list[Outgoing]:
        """Witnessed rules: re-sync ``node`` alone (``Supervisor.resync``, SYNC with a fresh
        random nonce) when ``why`` (its window used up, or its counts ignored: a node left
        answering a SYNC); only while its session is IDLE. Nobody else waits for it."""
        if not self.core.idle(node):
            return []
        info = self.nodes[node]
        info.resyncs, info.resynced_at = info.resyncs + 1, now
        log.warning("node %s: re-synced, %s", self.node_name(node), why)
        return self._carry_out(self.core.resync(node, now, secrets.randbits(16)), now)

    def _carry_out(self, actions: list[Action], now: int) -> list[Outgoing]:
        out: list[Outgoing] = []
        queue = actions  # grows at its end (a decision follows an ACK), read in order
        i = 0
        while i < len(queue):
            action = queue[i]
            i += 1
            if isinstance(action, Send):
                out.append(action.message)
            elif isinstance(action, Persist):
                self.ledger.dirty = True  # written once, at the step's end
            elif isinstance(action, Acknowledged):
                decide = self.core.abort if self.stopping else self.core.commit
                queue.extend(decide(action.node, now))
            elif isinstance(action, Resolved):
                self._resolved(action, now)
            elif isinstance(action, ReturnCredited):
                self.nodes[action.node].returns += 1
                self.heard.credited(action.node, action.amount, now)
            elif isinstance(action, Admitted):
                self._admitted(action)
            elif isinstance(action, AheadOfImage):
                self._ahead(action)
        return out

    def _ahead(self, action: AheadOfImage) -> None:
        self.nodes[action.node].ahead_of_image_uj += action.amount
        log.warning(
            "node %s holds %d debit numbers this state file never saw, with books that cannot "
            "say what it received: the file is older than its admission afresh; %s moved from "
            "the usable budget to its grants (the most those numbers could draw), a loss",
            self.node_name(action.node),
            action.numbers,
            format_energy(action.amount),
        )

    def _admitted(self, action: Admitted) -> None:
        info = self.nodes[action.node]
        info.admitted += 1
        self.witness.readmitted(action.node)  # its return numbers start again
        had_books = action.tx or action.seq  # what it held is gone with its record
        if had_books and action.node != self._resuming:  # a RESUME's is logged by ``_resume``
            log.warning(
                "node %s has no books (NV lost or replaced): admitted at tx %d, return %d; "
                "anything it held is written off",
                self.node_name(action.node),
                action.tx,
                action.seq,
            )

    def _resolved(self, action: Resolved, now: int) -> None:
        info = self.nodes[action.node]
        info.ended_at = now
        if info.requests:
            self.ready.add(action.node)
        if action.outcome is Outcome.COMMITTED:
            info.committed += 1
            info.committed_uj += action.amount
        elif action.outcome is Outcome.ABORTED:
            info.aborted += 1
        else:
            info.written_off += 1
        self._finish_request(
            action.node,
            {
                "node": self.node_name(action.node),
                "tx": action.tx,
                "outcome": action.outcome.name,
                "amount_uj": action.amount,
            },
        )

    def _finish_request(self, node: int, result: dict[str, Any]) -> None:
        info = self.nodes[node]
        if info.active_request is not None:
            info.active_request.reply(result)
            info.active_request = None

    def _flush(self, out: list[Outgoing]) -> list[Message]:
        """Write the state file once for everything decided in this step, before any of the
        step's frames leave (the caller sends ``out`` only after this returns). In a pass, hold
        them: ``end_pass`` writes and returns them."""
        if self._pass.depth:
            self._pass.held += out
            return []
        self.ledger.save_if_dirty()
        if any(isinstance(m, RawFrame) for m in out):  # ``_begin`` makes them in a pass only
            raise RuntimeError("frames encoded by the C core outside a loop pass")
        return cast(list[Message], out)

    # -- status ----------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        waiting = self.waiting()
        run = Run(
            now=self.now,
            uptime_us=self.now - self.started_at,
            stopping=self.stopping,
            listen_only=self.config.listen_only,
            fsync=self.config.fsync,
            injected_this_run=self.ledger.injected_this_run,
            granted_this_run=self.ledger.granted_total(),
            stopped_by_intrusion=self.stopped_by_intrusion,
            waiting_for_books=[self.node_name(n) for n in waiting],
            waiting_why=self.waiting_why(waiting) if waiting else None,
            started_without=self.started_without,
            variant_mismatch=self.rules_said.by_name(),
        )
        return self.report.status(run)

    def write_status(self) -> None:
        self.status_out.write(self.status())
