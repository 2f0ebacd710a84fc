"""The supervisor core compiled: firmware/'s C supervisor role behind ``core.Supervisor``'s
interface, for ``canergy supervisor --core c``.

One C call per frame, timer or request runs the hardened (or the witnessed) rules and Us, and
reports what each
session step did; this side turns that into the same actions the Python core returns (``Send``,
``Persist``, ``Acknowledged``, ``Resolved``, ``ReturnCredited``, ``Admitted``,
``AheadOfImage``) and keeps a Python
copy of the sessions it touched. Books, files, policies and intrusions stay in the service.
tests/test_ccore.py runs it side by side with ``core.Supervisor``, on the tests' sanitizer builds
of the library (``CompiledSupervisor(module=...)``).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any, cast

from canergy.ccore.calls import Answer, AuthAnswer, AuthPair
from canergy.ccore.grants import CompiledGrantCaps, fits
from canergy.ccore.joins import CompiledJoinHold
from canergy.ccore.witness import CompiledReturnGate
from canergy.codec import DEFAULT_ID_BASE, Codec
from canergy.core import witnessed
from canergy.core.actions import (
    Acknowledged,
    Action,
    Admitted,
    AheadOfImage,
    Persist,
    Resolved,
    ReturnCredited,
    Send,
)
from canergy.core.common import check_counters, check_life
from canergy.core.errors import LocalProtocolError
from canergy.core.gateway import Below, MakeDown, no_hold
from canergy.core.inputs import Begin
from canergy.core.state import Decision, Outcome, Phase, Session, SupervisorState
from canergy.core.supervisor import Supervisor, SupervisorCore
from canergy.core.timing import Timing
from canergy.core.variants import Variant, get_variant
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.policy import Limits, TopUp
from canergy.messages import (
    MAX_NODE,
    MIN_NODE,
    QUANTUM_UJ,
    Aborted,
    Ack,
    Committed,
    Debit,
    Direction,
    Join,
    Message,
    MsgType,
    Return,
    Telemetry,
    ToSupervisor,
)


class CoreMissing(RuntimeError):
    """The C core was asked for and is not built here."""


_CODES = {"uint8_t": "B", "uint16_t": "H", "uint32_t": "I", "int32_t": "i", "uint64_t": "Q"}


def _reader(ffi: Any, ctype: str, names: tuple[str, ...]) -> tuple[struct.Struct, int]:
    """A ``struct.Struct`` that reads ``names`` of ``ctype``, in that order, at the offsets the
    compiled library gives them (padding skipped), and the first one's offset: one unpack per
    record instead of an attribute lookup through cffi per field."""
    fields = dict(ffi.typeof(ctype).fields)
    start = at = fields[names[0]].offset
    codes = ["<"]
    for name in names:
        field = fields[name]
        if field.offset < at:
            raise CoreMissing(f"canergy.ccore: {ctype}.{name} is not after the fields before it")
        kind = field.type
        codes.append("x" * (field.offset - at))
        codes.append(f"{kind.length}s" if kind.kind == "array" else _CODES[kind.cname])
        at = field.offset + ffi.sizeof(kind)
    return struct.Struct("".join(codes)), start


_HELD = ("IDLE", "WAIT_ACK", "ACKED", "WAIT_CONFIRM", "SYNCING", "SYNC_BOOKS")


class _Binding:
    """What the core reads off one compiled module of ``canergy.ccore.build`` (``ffi``,
    ``lib``): the records' readers at the compiled offsets and the headers' values, each
    mapped to its Python name. Raises ``AttributeError``, ``KeyError`` or ``CoreMissing`` for a
    module built from other headers."""

    def __init__(self, module: Any) -> None:
        self.module = module  # kept: its id keys _BINDINGS
        self.ffi = ffi = module.ffi
        self.lib = lib = module.lib
        self.session, _ = _reader(
            ffi,
            "struct canergy_session",
            ("delivered_uj", "returned_uj", "deadline", "tx", "returns_credited", "reserved_uj",
             "resume_from", "resume_to", "resume_nonce", "witness", "join_tx", "join_seq",
             "join_nonce", "sync_nonce", "node", "phase", "decision", "tries", "resync"),
        )  # fmt: skip
        self.event, _ = _reader(
            ffi,
            "struct canergy_supervisor_event",
            ("tx", "amount_uj", "ahead_numbers", "node", "resolved", "flags"),
        )
        self.frame, _ = _reader(ffi, "struct canergy_frame", ("id", "dlc", "data"))
        self.auth_frame, _ = _reader(ffi, "struct canergy_auth_frame", ("id", "len", "data"))
        self.auth_frame_size = ffi.sizeof("struct canergy_auth_frame")
        self.auth_fd = lib.CANERGY_AUTH_FD
        self.auth_classic = lib.CANERGY_AUTH_CLASSIC
        self.to_supervisor = lib.CANERGY_TO_SUPERVISOR
        self.counts, self.counts_at = _reader(
            ffi, "struct canergy_supervisor_out", ("frame_count", "event_count", "persist")
        )
        self.session_size = ffi.sizeof("struct canergy_session")
        self.event_size = ffi.sizeof("struct canergy_supervisor_event")
        self.frame_size = ffi.sizeof("struct canergy_frame")
        self.sessions_at = ffi.offsetof("struct canergy_supervisor", "sessions")
        self.events_at = ffi.offsetof("struct canergy_supervisor_out", "events")
        self.frames_at = ffi.offsetof("struct canergy_supervisor_out", "frames")
        self.never = lib.CANERGY_NEVER
        self.ok = lib.CANERGY_DECODE_OK
        self.caller = lib.CANERGY_RX_CALLER
        self.not_can = lib.CANERGY_RX_NOT_CAN
        """``on_answer``'s status for an identifier no CAN frame carries: taken the usual way."""
        self.verdicts = (int(lib.CANERGY_HOST_HELD), int(lib.CANERGY_HOST_JOIN))
        """``on_answer``'s verdict bits for a RETURN the witness in C held and a JOIN held in C
        (canergy/host.h)."""
        self.phases = {getattr(lib, f"CANERGY_S_{name}"): Phase[name] for name in _HELD}
        """The phases a C session holds, by the value C gives them (enum canergy_session_phase)."""
        self.c_phases = {p: c for c, p in self.phases.items()}
        self.idle = self.c_phases[Phase.IDLE]
        self.decisions = {
            lib.CANERGY_DECIDE_NONE: Decision.NONE,
            lib.CANERGY_DECIDE_COMMIT: Decision.COMMIT,
            lib.CANERGY_DECIDE_ABORT: Decision.ABORT,
        }
        self.c_decisions = {d: c for c, d in self.decisions.items()}
        self.acknowledged = lib.CANERGY_SUP_ACKNOWLEDGED
        self.return_credited = lib.CANERGY_SUP_RETURN_CREDITED
        self.admitted = lib.CANERGY_SUP_ADMITTED
        self.ahead = lib.CANERGY_SUP_AHEAD
        self.outcomes = {
            lib.CANERGY_RESOLVED_COMMITTED: Outcome.COMMITTED,
            lib.CANERGY_RESOLVED_ABORTED: Outcome.ABORTED,
            lib.CANERGY_RESOLVED_WRITTEN_OFF: Outcome.WRITTEN_OFF,
        }
        self.errors = {
            lib.CANERGY_ERR_ARGUMENT: "argument",
            lib.CANERGY_ERR_PHASE: "phase",
            lib.CANERGY_ERR_AMOUNT: "amount",
            lib.CANERGY_ERR_END: "end of the numbering",
            lib.CANERGY_ERR_WINDOW: "window",
        }
        self.c_rules = {
            "hardened": lib.CANERGY_RULES_HARDENED,
            "witnessed": lib.CANERGY_RULES_WITNESSED,
        }
        """The rule sets the C supervisor runs (enum canergy_rules)."""


_BINDINGS: dict[int, _Binding] = {}


def _binding(module: Any) -> _Binding:
    """The module's ``_Binding``, made once per module."""
    if (known := _BINDINGS.get(id(module))) is None:
        try:
            known = _BINDINGS[id(module)] = _Binding(module)
        except (AttributeError, KeyError, CoreMissing) as exc:
            raise CoreMissing(
                f"the compiled supervisor core {module.__name__} does not match this canergy "
                f"({exc}): rebuild it (python -m canergy.ccore.build in a checkout)"
            ) from exc
    return known


try:
    from canergy.ccore import _supervisor as _RELEASE  # type: ignore[attr-defined]
except ImportError as exc:  # built by pip install where a compiler exists
    _MISSING: str | None = (
        f"the compiled supervisor core is not built ({exc}): install canergy where a C compiler "
        "exists, or run python -m canergy.ccore.build in a checkout"
    )
else:
    try:
        _binding(_RELEASE)
        _MISSING = None
    except CoreMissing as exc:  # built from other headers
        _MISSING = str(exc)


def missing() -> str | None:
    """Why the C core cannot run here, or None when it can."""
    return _MISSING


_ID_LIMIT = 1 << 29
_RULES = ("hardened", "witnessed")


class CompiledSupervisor:
    """``core.Supervisor`` (hardened or witnessed rules) with the rules, Us and the codec in C."""

    implementation = "c"

    def __init__(
        self,
        nodes: Iterable[int],
        initial: int,
        *,
        timing: Timing | None = None,
        state: SupervisorState | None = None,
        id_base: int | None = None,
        variant: str | Variant = "hardened",
        start_without: Iterable[int] = (),
        module: Any = None,
    ) -> None:
        """``variant``: by name or as a ``Variant``; ``start_without``: as
        ``core.Supervisor``'s (the operator's risk, said there).
        ``module``: the build of the library to run, a module of ``canergy.ccore.build`` (its
        ``ffi`` and ``lib``); by default the release module, ``canergy.ccore._supervisor`` (the
        tests hand it their sanitizer builds)."""
        if module is None:
            if _MISSING is not None:
                raise CoreMissing(_MISSING)
            module = _RELEASE
        self._b = b = _binding(module)
        ffi, lib = b.ffi, b.lib
        self._lib = lib
        self._answer = lib.canergy_host_answer
        variant = variant if isinstance(variant, str) else variant.name
        if variant not in _RULES:
            raise ValueError(f"the C core runs the rules {', '.join(_RULES)}, not {variant!r}")
        self.variant = get_variant(variant)
        self.timing = timing or Timing()
        node_list = sorted(set(nodes))
        if not node_list or not all(MIN_NODE <= n <= MAX_NODE for n in node_list):
            raise ValueError(f"the C core takes node ids {MIN_NODE}-{MAX_NODE} (one bus)")
        if initial < 0:
            raise ValueError("initial budget must be >= 0")
        if not 0 <= self.timing.response_timeout_us < 2**32 or not 0 <= self.timing.retries < 256:
            raise ValueError("the C core needs a response timeout below 2^32 µs, retries < 256")
        if not 0 < self.timing.window < 0x8000:
            raise ValueError("the C core needs a window of 1-32767 transactions")
        self.codec = Codec() if id_base is None else Codec(id_base)
        self._decode = partial(self.codec.decode, direction=Direction.TO_CLIENT)
        self._sup = ffi.new("struct canergy_supervisor *")
        self._out = ffi.new("struct canergy_supervisor_out *")
        self._sup_bytes = ffi.buffer(self._sup)  # live views of the C memory
        self._out_bytes = ffi.buffer(self._out)
        self._msg = ffi.new("struct canergy_msg *")
        self.tables: Any = ffi.new("struct canergy_host_tables *")
        """The service's tables in C (``heard_table``, ``return_gate``, ``join_hold``), which
        ``on_answer`` runs once all three are made; their records are kept alive here."""
        self._kept: dict[str, Any] = {}
        self._tables: Any = ffi.NULL
        cfg = ffi.new("struct canergy_supervisor_config *")
        cfg.id_base = self.codec.id_base
        cfg.timing.response_timeout_us = self.timing.response_timeout_us
        cfg.timing.retries = self.timing.retries
        cfg.timing.rules = b.c_rules[variant]
        cfg.timing.window = self.timing.window
        ids = ffi.new("uint8_t[]", node_list)
        rc = lib.canergy_supervisor_init(self._sup, cfg, ids, len(node_list), initial)
        if rc != lib.CANERGY_OK:
            raise ValueError(
                f"the C core refused {len(node_list)} nodes (it holds "
                f"{lib.CANERGY_SUPERVISOR_NODES})"
            )
        self.start_without = frozenset(start_without)
        if not self.start_without <= set(node_list):
            raise ValueError("start_without names nodes this supervisor does not manage")
        for n in self.start_without:
            lib.canergy_supervisor_start_without(self._sup, n)
        self._initial = initial
        self._index = {n: i for i, n in enumerate(node_list)}
        self._timer: int | None = None
        self._timer_known = True
        """``get_timer``'s answer, kept until a call into C that may move a deadline (the C
        side scans every session for it, on data gone cold since the last pass). The loop's
        thread alone asks for it, as it alone makes those calls."""
        self._sessions = [Session(n) for n in node_list]
        """Python copies of the C sessions, read whole only when asked for (``session``,
        ``state``): a call that changed one marks it stale. The loop's thread alone makes
        both (the SDO audit's comparison is posted to it, ``canergy.live.serve``)."""
        self._stale: set[int] = set()
        """Indexes of the sessions a call changed since they were last read."""
        if state is not None:
            self._load(state)

    # -- state -----------------------------------------------------------------------------
    @property
    def nodes(self) -> tuple[int, ...]:
        return tuple(self._index)

    @property
    def state(self) -> SupervisorState:
        sup = self._sup
        self._read_stale()
        return SupervisorState(
            self._initial, sup.usable_uj, sup.injected_uj, tuple(self._sessions), sup.withdrawn_uj
        )

    @property
    def usable(self) -> int:
        return int(self._sup.usable_uj)

    def session(self, node: int) -> Session:
        i = self._index[node]
        if i in self._stale:
            self._stale.discard(i)
            self._sessions[i] = self._read(i)
        return self._sessions[i]

    def idle(self, node: int) -> bool:
        return bool(self._sup.sessions[self._index[node]].phase == self._b.idle)

    def _read_stale(self) -> None:
        """Read every session a call changed since it was last read."""
        stale, sessions = self._stale, self._sessions
        while stale:
            i = stale.pop()
            sessions[i] = self._read(i)

    def hand_usable(self, other: CompiledSupervisor) -> None:
        """Move all of Us (a debt too) into ``other``'s: one pool over several buses
        (``canergy.ccore.buses``). Nothing else changes: the two Us summed stay as they were."""
        if other is not self:
            moved = int(self._sup.usable_uj)
            self._sup.usable_uj = 0
            other._sup.usable_uj += moved

    def is_quiescent(self) -> bool:
        self._read_stale()
        return all(s.phase is Phase.IDLE for s in self._sessions)

    def unconfirmed(self) -> tuple[int, ...]:
        """The nodes whose books this start waits for before any grant (``core.Supervisor``'s),
        as the C supervisor counts them."""
        nodes = self._b.ffi.new("uint8_t[]", max(1, len(self._sessions)))
        return tuple(nodes[0 : self._lib.canergy_supervisor_unconfirmed(self._sup, nodes)])

    def _load(self, st: SupervisorState) -> None:
        """Take a saved state (the state file's): Us, injected, withdrawn and every session's
        record."""
        if tuple(s.node for s in st.sessions) != self.nodes:
            raise ValueError("the state's nodes are not this supervisor's")
        sup, b = self._sup, self._b
        sup.usable_uj, sup.injected_uj, sup.withdrawn_uj = st.usable, st.injected, st.withdrawn
        self._initial = st.initial
        for i, s in enumerate(st.sessions):
            if s.phase not in b.c_phases:
                raise ValueError(f"node {s.node}: a record the C core cannot hold")
            check_counters(s)
            c = sup.sessions[i]
            c.phase, c.tx, c.reserved_uj = b.c_phases[s.phase], s.tx, s.reserved
            c.delivered_uj, c.returned_uj, c.decision = (
                s.delivered,
                s.returned,
                b.c_decisions[s.decision],
            )
            c.returns_credited, c.tries = s.returns_credited, s.tries
            c.resume_from, c.resume_to = s.resume_from % 2**32, s.resume_to % 2**32
            c.resume_nonce, c.witness, c.sync_nonce = s.resume_nonce, s.witness, s.sync_nonce
            c.join_tx, c.join_seq, c.join_nonce = s.join_tx, s.join_seq, s.join_nonce
            c.deadline = b.never if s.deadline is None else s.deadline
            c.resync = s.resync
            self._sessions[i] = self._read(i)
        self._stale.clear()
        self._timer_known = False

    def _read(self, i: int) -> Session:
        b = self._b
        (
            delivered, returned, deadline, tx, credited, reserved,
            resume_from, resume_to, resume_nonce, witness, join_tx, join_seq, join_nonce,
            sync_nonce, node, phase, decision, tries, resync,
        ) = b.session.unpack_from(self._sup_bytes, b.sessions_at + i * b.session_size)  # fmt: skip
        resume_from = resume_to - (resume_to - resume_from) % 2**32  # Python's: below resume_to
        return Session(
            node,
            b.phases[phase],
            tx,
            reserved,
            delivered,
            b.decisions[decision],
            credited,
            returned,
            tries,
            None if deadline == b.never else deadline,
            resume_nonce,
            resume_from,
            resume_to,
            witness,
            sync_nonce,
            join_nonce,
            join_tx,
            join_seq,
            bool(resync),
        )

    # -- requests --------------------------------------------------------------------------
    def begin(self, node: int, amount: int, now: int) -> list[Action]:
        """Reserve ``amount`` µJ from Us and send node ``node`` an intention."""
        self._begin(node, amount, now)
        return self._actions()

    def begin_encoded(
        self, node: int, amount: int, now: int
    ) -> tuple[list[Action], list[tuple[int, bytes]]]:
        """``begin`` with its INTENTION as the C codec encoded it (``_frames``) instead of a
        ``Send``: the fast path's loop sends those bytes as they are."""
        self._begin(node, amount, now)
        return self._fast_out()

    def _begin(self, node: int, amount: int, now: int) -> None:
        self._managed(node)
        if not 0 < amount < 2**32:
            raise LocalProtocolError(f"amount {amount} µJ is not a grant one frame carries")
        self._timer_known = False  # deadlines may move
        lib = self._lib
        rc = lib.canergy_supervisor_begin(self._sup, node, amount, now, self._out)
        if rc == lib.CANERGY_ERR_UNCONFIRMED:
            raise LocalProtocolError(
                "no grant before every node has confirmed its books after this start: waiting "
                f"for node(s) {', '.join(map(str, self.unconfirmed()))}"
            )
        if rc == lib.CANERGY_ERR_WINDOW:
            witnessed.begin(self.timing, self.session(node), Begin(amount), now)  # its words
        if rc == lib.CANERGY_ERR_AMOUNT and amount <= self._sup.usable_uj:
            raise LocalProtocolError(f"amount {amount} µJ is not a whole mJ up to 65,535 mJ")
        if rc == lib.CANERGY_ERR_AMOUNT:
            raise LocalProtocolError(f"amount {amount} µJ exceeds usable {self.usable} µJ")
        if rc == lib.CANERGY_ERR_END:
            check_life(self.session(node))  # the Python core's words
        self._check(rc, node, "begin")

    def commit(self, node: int, now: int) -> list[Action]:
        self._managed(node)
        self._timer_known = False  # deadlines may move
        rc = self._lib.canergy_supervisor_decide(self._sup, node, True, now, self._out)
        return self._checked(rc, node, "commit")

    def abort(self, node: int, now: int) -> list[Action]:
        self._managed(node)
        self._timer_known = False  # deadlines may move
        rc = self._lib.canergy_supervisor_decide(self._sup, node, False, now, self._out)
        return self._checked(rc, node, "abort")

    def receive(self, msg: ToSupervisor, now: int) -> list[Action]:
        """Feed a decoded client message; messages for unknown nodes are ignored."""
        if msg.node not in self._index:
            return []
        m = self._msg
        m.type, m.node = msg.TYPE, msg.node
        if isinstance(msg, Ack | Committed | Aborted):
            m.tx = msg.tx
        elif isinstance(msg, Return):
            m.seq, m.amount_mj = msg.seq, msg.amount_mj
        elif isinstance(msg, Join):
            m.nonce = msg.nonce
        elif isinstance(msg, Debit):  # the witnessed rules take it; the hardened ones ignore it
            m.nonce, m.flags, m.seq, m.amount_mj = msg.nonce, msg.flags, msg.seq, msg.amount_mj
        else:  # as the Python table: no rule takes it (a TELEMETRY is the service's)
            raise LocalProtocolError(
                f"{self.variant.name} supervisor: no rule for {type(msg).__name__}"
            )
        self._timer_known = False  # deadlines may move
        c = self._sup.sessions[self._index[msg.node]]
        returned = int(c.returned_uj)  # a RESUME's credit: what it grew by
        self._lib.canergy_supervisor_on_msg(self._sup, m, now, self._out)
        resumed = isinstance(msg, Debit) and msg.is_resume
        return self._actions(resumed=resumed, returned=returned)

    def heard_table(self, lost_after_us: int) -> CompiledHeard:
        """The TELEMETRY table (``canergy.live.supervisor.telemetry``) in C, one record per
        session, new at each call: from then on ``on_answer`` takes a TELEMETRY of a managed
        node into it in the same call that decodes the frame."""
        if not 0 <= lost_after_us < 2**64:
            raise ValueError("lost_after_us must fit 64 bits")
        t = self.tables
        records = self._keep(
            "heard", self._b.ffi.new("struct canergy_heard[]", len(self._sessions))
        )
        t.heard, t.lost_after_us = records, lost_after_us
        self._ready()
        return CompiledHeard(self, records, lost_after_us)

    def return_gate(self, hold_us: int, block_us: int, hold: bool) -> CompiledReturnGate:
        """The witness (``canergy.live.supervisor.witness.ReturnGate``'s interface) in C, one
        record per session, new at each call: from then on ``on_answer`` takes a TELEMETRY into it
        too, and holds a fresh RETURN there (``hold``: detection mode, without a key) or hands
        it to the rules, in the call that decodes it."""
        t = self.tables
        before = self._b.ffi.addressof(t, "witness_before")
        gate = self._keep("witness", CompiledReturnGate(self, hold_us, block_us, before))
        t.witness, t.hold = gate.records, hold
        self._ready()
        return cast(CompiledReturnGate, gate)

    def join_hold(
        self,
        hold_us: int,
        local_nodes: frozenset[int],
        intrusions: Intrusions,
        refusals: Refusals,
        authenticated: Callable[[], bool],
    ) -> CompiledJoinHold:
        """The held JOINs (``canergy.live.supervisor.joins.JoinHold``'s interface) in C, one
        record per session, new at each call: from then on ``on_answer`` holds a JOIN there and
        takes a TELEMETRY into them too, in the call that decodes it."""
        t = self.tables
        joins = CompiledJoinHold(self, hold_us, local_nodes, intrusions, refusals, authenticated)
        holds = self._b.ffi.new("uint64_t[]", [joins.hold_for(n) for n in self._index])
        self._keep("joins", (joins, holds))
        t.joins, t.join_hold_us = joins.records, holds
        self._ready()
        return joins

    def _keep(self, table: str, records: Any) -> Any:
        """Keep a table's records alive while C points at them (a table made again, for a
        new service over this core, replaces the one before)."""
        self._kept[table] = records
        return records

    def _ready(self) -> None:
        """``on_answer`` runs the tables once every one of them is made."""
        t, null = self.tables, self._b.ffi.NULL
        if null not in (t.heard, t.witness, t.joins):
            self._tables = t

    @property
    def verdicts(self) -> tuple[int, int]:
        """The verdict bits ``on_answer`` gives a RETURN held and a JOIN held (canergy/host.h)."""
        return self._b.verdicts

    def grant_caps(self, limits: Limits, policy: TopUp | None) -> CompiledGrantCaps | None:
        """The grant caps (``canergy.live.supervisor.grants.GrantCaps``) in C, or None for
        limits beyond what they take exactly (``canergy.ccore.grants.fits``)."""
        return CompiledGrantCaps(self._b.module, limits, policy) if fits(limits, policy) else None

    def on_answer(
        self,
        arbitration_id: int,
        data: bytes | bytearray,
        extended: bool,
        remote: bool,
        now: int,
        abort: bool,
    ) -> tuple[int, list[Action], list[tuple[int, bytes]], Message | None, int]:
        """A received frame on the fast path (one C call: decode, rules, the decision on an ACK,
        encode): its status and, when it was an answer the rules took (ACK, COMMITTED, ABORTED
        of a managed node), their actions and the frames to send, encoded. A TELEMETRY, RETURN,
        JOIN or DEBIT of a managed node applies nothing and comes back decoded (by the C codec,
        which the Python one's tests fuzz against) for the caller's usual handling. Once the
        TELEMETRY table and the witness are made in C (``heard_table``, ``return_gate``), a
        TELEMETRY was taken by both (the last element: the table's verdict, ``telemetry.TAKEN``
        and ``BEYOND_BOOKS`` bits, with the witness's findings shifted left by 8; the record
        as it was before in ``return_gate().before``), and a RETURN the books allow was ruled
        (status 0, as an answer) or held by the witness (``verdicts[0]`` with its verdict); 0
        otherwise. Any other
        status (an answer ahead of the session, a decode status, another node, an identifier no
        CAN frame carries: CANERGY_RX_NOT_CAN) applied nothing and
        decoded nothing: the caller takes the frame its usual way, where it is judged, counted
        or reported."""
        if not 0 <= arbitration_id < _ID_LIMIT:  # no CAN identifier (another transport's)
            return self._b.not_can, [], [], None, 0
        m = self._msg
        kind = (1 if extended else 0) | (2 if remote else 0)
        payload = data if type(data) is bytes else bytes(data)  # cffi takes bytes as they are
        self._timer_known = False  # deadlines may move
        t = self._tables
        status = self._answer(
            self._sup, t, arbitration_id, kind, payload, len(payload), now, abort, self._out, m
        )
        b = self._b
        if status == b.ok:
            actions, frames = self._fast_out()
            return status, actions, frames, None, 0
        if status != b.caller:
            return status, [], [], None, 0
        msg: Message
        if (kind := m.type) == MsgType.TELEMETRY:  # the wire's type code, the same in both codecs
            msg = Telemetry(m.node, m.level_mj, m.flags, m.seq, m.witness)
        elif kind == MsgType.RETURN:
            msg = Return(m.node, m.seq, m.amount_mj)
        elif kind == MsgType.DEBIT:
            msg = Debit(m.node, m.nonce, m.flags, m.seq, m.amount_mj)
        else:
            msg = Join(m.node, m.nonce)
        return status, [], [], msg, 0 if t == self._b.ffi.NULL else t.verdict

    def answer_on(self, bus: int) -> Answer:
        """The frame path of bus ``bus`` (``on_answer``): this supervisor has one bus, 0."""
        if bus:
            raise ValueError(f"the C core on one bus has no bus {bus}")
        return self.on_answer

    def auth_answer_on(self, bus: int) -> AuthAnswer:
        """The frame path with a key of bus ``bus`` (``on_auth_answer``): this supervisor has
        one bus, 0."""
        if bus:
            raise ValueError(f"the C core on one bus has no bus {bus}")
        return self.on_auth_answer

    def auth_pair_on(self, bus: int) -> AuthPair:
        """The classic layout's frame path with a key of bus ``bus`` (``on_auth_pair``): this
        supervisor has one bus, 0."""
        if bus:
            raise ValueError(f"the C core on one bus has no bus {bus}")
        return self.on_auth_pair

    def use_keys(
        self, key_for: Callable[[int], bytes], *, classic: bool = False, bus: int | None = None
    ) -> None:
        """Authenticated mode: each managed node's key (``key_for(node)``, 16 bytes, as
        ``FrameAuth`` takes them) set up in C for ``on_auth_answer`` (FD layout) or, with
        ``classic``, ``on_auth_pair`` (classic layout); ``begin_protected`` in either.
        ``bus``: as ``CompiledBuses.use_keys`` takes it (this supervisor has one bus, 0)."""
        if bus:
            raise ValueError(f"the C core on one bus has no bus {bus}")
        b = self._b
        count = len(self._sessions)
        keys = b.ffi.new("struct canergy_auth[]", count)
        layout = b.auth_classic if classic else b.auth_fd
        for i, node in enumerate(self._index):
            key = key_for(node)
            rc = self._lib.canergy_auth_init(
                keys + i, key, self.codec.id_base, node, layout, b.to_supervisor
            )
            if rc != self._lib.CANERGY_OK or len(key) != 16:
                raise ValueError(f"node {node}: no 16-byte key the C library takes")
        self._keys = keys
        frames = 2 * self._lib.CANERGY_SUPERVISOR_NODES  # classic: each frame and its MAC frame
        self._sent = b.ffi.new("struct canergy_auth_frame[]", frames)
        self._sent_bytes = b.ffi.buffer(self._sent)
        self._sent_count = b.ffi.new("uint8_t *")
        self._fv = b.ffi.new("uint32_t *")

    def on_auth_answer(
        self,
        arbitration_id: int,
        data: bytes | bytearray,
        extended: bool,
        remote: bool,
        now: int,
        abort: bool,
    ) -> tuple[int, list[Action], list[tuple[int, bytes]], int]:
        """``on_answer`` in authenticated mode, FD layout (``use_keys`` first), in one C call:
        an ACK, COMMITTED or ABORTED of a managed node verified as ``FrameAuth`` verifies it
        (MAC, freshness against the session's counters), the rules, and each frame they send
        protected (FD frames, ready to send). Status 0: taken, with the actions, the frames and
        the received frame's FV. Any other status: nothing changed, nothing decoded (any other
        frame, a refused one, an answer ahead of the session): the caller's usual path judges
        and counts it."""
        if not 0 <= arbitration_id < _ID_LIMIT:
            return self._b.not_can, [], [], 0
        kind = (1 if extended else 0) | (2 if remote else 0)
        payload = data if type(data) is bytes else bytes(data)
        status = self._lib.canergy_host_auth_answer(
            self._sup, self._keys, arbitration_id, kind, payload, len(payload), now, abort,
            self._out, self._sent, self._sent_count, self._fv,
        )  # fmt: skip
        if status != self._b.ok:
            return status, [], [], 0
        self._timer_known = False  # deadlines moved
        return status, self._actions(fast=True), self._protected(), int(self._fv[0])

    def on_auth_pair(
        self,
        data_id: int,
        data: bytes,
        mac_id: int,
        mac: bytes | bytearray,
        extended: bool,
        remote: bool,
        now: int,
        abort: bool,
    ) -> tuple[int, list[Action], list[tuple[int, bytes]], int]:
        """``on_auth_answer`` in the classic layout (``use_keys(classic=True)`` first): a
        message (``data_id``, ``data``: the data frame ``FrameAuth`` keeps until its MAC frame)
        and the MAC frame that came for it (``mac_id``, ``mac``, its flags), in one C call. An
        ACK, COMMITTED or ABORTED of a managed node verified as ``FrameAuth`` verifies the
        pair, the rules, and each frame they send protected (the classic frame, then its MAC
        frame). Status 0: taken, with the actions, the frames and the pair's FV. Any other
        status: nothing changed (C keeps no message waiting): the caller's usual path judges
        and counts the pair."""
        if not 0 <= mac_id < _ID_LIMIT:
            return self._b.not_can, [], [], 0
        kind = (1 if extended else 0) | (2 if remote else 0)
        payload = mac if type(mac) is bytes else bytes(mac)
        status = self._lib.canergy_host_auth_pair(
            self._sup, self._keys, data_id, data, len(data), mac_id, kind, payload, len(payload),
            now, abort, self._out, self._sent, self._sent_count, self._fv,
        )  # fmt: skip
        if status != self._b.ok:
            return status, [], [], 0
        self._timer_known = False  # deadlines moved
        return status, self._actions(fast=True), self._protected(), int(self._fv[0])

    def begin_protected(
        self, node: int, amount: int, now: int
    ) -> tuple[list[Action], list[tuple[int, bytes]]]:
        """``begin_encoded`` in authenticated mode (``use_keys`` first): the INTENTION
        protected in C under the node's key, ready to send (FD: one frame; classic: the frame,
        then its MAC frame)."""
        self._begin(node, amount, now)
        self._lib.canergy_host_auth_protect(
            self._sup, self._keys, self._out, self._sent, self._sent_count
        )
        return self._actions(fast=True), self._protected()

    def _protected(self) -> list[tuple[int, bytes]]:
        """The last call's protected frames as (identifier, data): FD frames, or classic
        frames each followed by its MAC frame."""
        b, raw = self._b, self._sent_bytes
        frames = []
        for k in range(self._sent_count[0]):
            ident, length, body = b.auth_frame.unpack_from(raw, k * b.auth_frame_size)
            frames.append((ident, body[:length]))
        return frames

    def get_timer(self) -> int | None:
        if not self._timer_known:
            deadline: int = self._lib.canergy_supervisor_deadline(self._sup)
            self._timer = None if deadline == self._b.never else deadline
            self._timer_known = True
        return self._timer

    def handle_timer(self, now: int) -> list[Action]:
        self._timer_known = False  # deadlines may move
        self._lib.canergy_supervisor_on_timer(self._sup, now, self._out)
        return self._actions()

    def inject(self, amount: int) -> None:
        if amount <= 0:
            raise LocalProtocolError("injected energy must be positive")
        if self._lib.canergy_supervisor_inject(self._sup, amount) != self._lib.CANERGY_OK:
            raise LocalProtocolError(f"cannot inject {amount} µJ into {self.usable} µJ usable")

    def withdraw(self, amount: int) -> None:
        """Take energy out of Us to outside (counted as withdrawn): a gateway's return
        upstream (``core.Supervisor.withdraw``)."""
        if self._lib.canergy_supervisor_withdraw(self._sup, max(amount, 0)) != self._lib.CANERGY_OK:
            raise LocalProtocolError(f"cannot withdraw {amount} µJ of {self.usable} µJ usable")

    def power_loss(self, now: int, nonce: int = 0) -> None:
        """Lose volatile state and restart from the persistent record; ``nonce``: as
        ``core.Supervisor.power_loss`` (witnessed: the SYNC's)."""
        self._timer_known = False  # deadlines may move
        self._lib.canergy_supervisor_start(self._sup, nonce, now, self._out)
        self._sessions = [self._read(i) for i in range(len(self._sessions))]
        self._stale.clear()

    def resync(self, node: int, now: int, nonce: int) -> list[Action]:
        """``core.Supervisor.resync``: re-sync node ``node`` alone, SYNC(``nonce``) sent."""
        self._managed(node)
        if not self.variant.lifts_tx:
            raise LocalProtocolError(f"the {self.variant.name} rules have no re-sync")
        self._timer_known = False  # deadlines may move
        rc = self._lib.canergy_supervisor_resync(self._sup, node, nonce, now, self._out)
        if rc == self._lib.CANERGY_ERR_PHASE:
            witnessed.resync_session(self.timing, self.session(node), nonce, now)  # its words
        return self._checked(rc, node, "re-sync")

    # -- internals -------------------------------------------------------------------------
    def _managed(self, node: int) -> None:
        if node not in self._index:
            raise LocalProtocolError(f"node {node} is not managed by this supervisor")

    def _checked(self, rc: int, node: int, what: str) -> list[Action]:
        self._check(rc, node, what)
        return self._actions()

    def _check(self, rc: int, node: int, what: str) -> None:
        if rc != self._lib.CANERGY_OK:
            phase = self.session(node).phase.name
            raise LocalProtocolError(f"cannot {what} node {node} in {phase} ({self._b.errors[rc]})")

    def _fast_out(self) -> tuple[list[Action], list[tuple[int, bytes]]]:
        """``_actions(fast=True)`` and ``_frames()`` with the output's counts read once (the
        frame path's every answer and grant)."""
        raw, b = self._out_bytes, self._b
        counts = b.counts.unpack_from(raw, b.counts_at)
        frame, at, size = b.frame.unpack_from, b.frames_at, b.frame_size
        frames = []
        for k in range(counts[0]):
            arbitration_id, dlc, data = frame(raw, at + k * size)
            frames.append((arbitration_id, data[:dlc]))
        return self._actions(fast=True, counts=counts), frames

    def _actions(
        self,
        *,
        fast: bool = False,
        resumed: bool = False,
        returned: int | None = None,
        counts: tuple[int, int, int] | None = None,
    ) -> list[Action]:
        """The last call's output as the Python core's actions, in its order. ``fast``
        (``on_answer``): no ``Acknowledged`` (decided in C already) and no ``Send`` (the
        frames go out as C encoded them, ``_frames``). ``resumed``: a RESUME, which credits a
        pending return numbered one below the number it then voids; ``returned``: its node's
        returned µJ before the call (an event that resolves and credits carries the Ts, and
        the credit is what returned grew by). ``counts``: the output's counts, read already."""
        raw, b = self._out_bytes, self._b
        frames, events, persist = (
            b.counts.unpack_from(raw, b.counts_at) if counts is None else counts
        )
        actions: list[Action] = [Persist()] if persist else []
        sent = 0
        sessions = self._sup.sessions
        for k in range(events):
            tx, amount, ahead, node, resolved, flags = b.event.unpack_from(
                raw, b.events_at + k * b.event_size
            )
            i = self._index[node]
            self._stale.add(i)  # read when asked for (``session``)
            if flags & b.acknowledged and not fast:
                actions.append(Acknowledged(node, tx))
            if resolved:
                actions.append(Resolved(node, tx, b.outcomes[resolved], amount))
            if flags & b.return_credited:  # the event's amount, or what returned grew by
                c = sessions[i]
                credited = amount
                if resolved:
                    assert returned is not None, "a RESUME's credit needs returned before it"
                    credited = int(c.returned_uj) - returned
                actions.append(ReturnCredited(node, c.returns_credited - resumed, credited))
            if flags & b.ahead:  # before the ADMIT it precedes, as Python's take_counts
                actions.append(AheadOfImage(node, ahead))
            if flags & b.admitted:
                c = sessions[i]
                actions.append(Admitted(node, c.tx, c.returns_credited))
            if sent < frames and not fast:
                arbitration_id, dlc, data = b.frame.unpack_from(
                    raw, b.frames_at + sent * b.frame_size
                )
                if arbitration_id & 0xFF == node:  # a step sends at most one frame, its node's
                    actions.append(Send(self._decode(arbitration_id, data[:dlc])))
                    sent += 1
        return actions

    def _frames(self) -> list[tuple[int, bytes]]:
        """The last call's frames as (identifier, data), encoded by the C codec."""
        raw, b = self._out_bytes, self._b
        frames = []
        for k in range(b.counts.unpack_from(raw, b.counts_at)[0]):
            arbitration_id, dlc, data = b.frame.unpack_from(raw, b.frames_at + k * b.frame_size)
            frames.append((arbitration_id, data[:dlc]))
        return frames


class CompiledBelow(CompiledSupervisor):
    """A gateway's supervisor role on the compiled core (``core.gateway.Below``'s twin, for
    ``canergy gateway --core c``): no grant begins, on any path, while ``hold`` says why not
    (the gateway's own start, not yet confirmed above)."""

    hold: Callable[[], str | None] = staticmethod(no_hold)
    """Why no grant may begin below (None: it may); set by the gateway."""

    def _begin(self, node: int, amount: int, now: int) -> None:
        if (why := self.hold()) is not None:
            raise LocalProtocolError(why)
        super()._begin(node, amount, now)


class CompiledHeard:
    """The compiled core's TELEMETRY table (``CompiledSupervisor.heard_table``): the methods of
    ``telemetry.HeardTable`` over the records in C."""

    implementation = "c"

    def __init__(self, core: CompiledSupervisor, records: Any, lost_after_us: int) -> None:
        self._core = core
        self._records = records
        self._lost_after_us = lost_after_us
        self._lib = core._lib
        self._views = {n: _HeardView(records + i) for n, i in core._index.items()}

    def of(self, node: int) -> _HeardView:
        return self._views[node]

    def telemetry(self, node: int, s: Session, level_mj: int, flags: int, now: int) -> int:
        """A TELEMETRY taken the usual way (decoded in Python): into the same table in C."""
        core = self._core
        i = core._index[node]
        m = core._msg
        m.type, m.node, m.level_mj, m.flags = MsgType.TELEMETRY, node, level_mj, flags
        sessions = core._sup.sessions
        return int(
            self._lib.canergy_heard_telemetry(
                self._records + i, sessions + i, m, now, self._lost_after_us
            )
        )

    def credited(self, node: int, amount_uj: int, now: int) -> None:
        i = self._core._index[node]
        self._lib.canergy_heard_credited(self._records + i, amount_uj, now, self._lost_after_us)


class _HeardView:
    """One node's record in C with ``telemetry.Heard``'s attributes."""

    __slots__ = ("_h",)

    def __init__(self, record: Any) -> None:
        self._h = record

    @property
    def level(self) -> int | None:
        h = self._h
        return int(h.level_mj) * QUANTUM_UJ if h.has_level else None

    @level.setter
    def level(self, value: int | None) -> None:
        if value is not None:
            raise ValueError("a level is only ever set by a TELEMETRY")
        self._h.has_level = False

    @property
    def level_at(self) -> int | None:
        h = self._h
        return int(h.level_at) if h.has_level_at else None

    @property
    def flags(self) -> int:
        return int(self._h.flags)

    @property
    def heard_at(self) -> int | None:
        h = self._h
        return int(h.heard_at) if h.has_heard else None

    @heard_at.setter
    def heard_at(self, now: int) -> None:
        h = self._h
        h.heard_at, h.has_heard = now, True

    @property
    def telemetry(self) -> int:
        return int(self._h.telemetry)

    @property
    def recent(self) -> list[tuple[int, int]]:
        h = self._h
        return [(int(h.recent_at[k]), int(h.recent_uj[k])) for k in range(h.recent_count)]


def make_supervisor(
    core: str,
    nodes: Iterable[int],
    initial: int,
    *,
    variant: str = "hardened",
    timing: Timing | None = None,
    state: SupervisorState | None = None,
    id_base: int | None = None,
    start_without: Iterable[int] = (),
    buses: bool = False,
) -> SupervisorCore:
    """A supervisor core by name: "python" (``core.Supervisor``, any variant) or "c";
    ``id_base``: the bus's identifier block (the C core encodes and decodes frames itself);
    ``buses``: ``nodes`` are session keys of named buses (``canergy.bus_keys``), for the C core
    one C supervisor per bus (``canergy.ccore.buses``)."""
    if core == "c":
        compiled: Callable[..., SupervisorCore] = CompiledSupervisor
        if buses:
            from canergy.ccore.buses import CompiledBuses

            compiled = CompiledBuses
        return compiled(
            nodes,
            initial,
            timing=timing,
            state=state,
            id_base=id_base,
            variant=variant,
            start_without=start_without,
        )
    if core != "python":
        raise ValueError(f"unknown core {core!r}: c or python")
    return Supervisor(
        nodes,
        initial,
        variant=variant,
        timing=timing,
        state=state,
        start_without=start_without,
        id_base=DEFAULT_ID_BASE if id_base is None else id_base,
    )


def make_below(core: str, id_base: int | None = None) -> MakeDown | None:
    """What makes a gateway's supervisor role (``core.gateway.Gateway(below=)``) by core name:
    "c" (``CompiledBelow``) or "python" (the gateway's own ``Below``; None: on the default
    block), each on the bus's identifier block ``id_base`` (its frame path's)."""
    if core == "c":
        return partial(CompiledBelow, id_base=id_base)
    if core != "python":
        raise ValueError(f"unknown core {core!r}: c or python")
    return None if id_base is None else partial(Below, id_base=id_base)
