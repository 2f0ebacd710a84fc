"""The supervisor's non-volatile record as a JSON file, replaced atomically on every change.

Only what the core marks persistent is kept: budgets, and per node the transaction number,
phase, reservation, decision, delivered count and return counters. Retry counts and deadlines
are volatile; on load every session restarts through the rules' ``power_loss``.

Version 2 adds ``checksum``, ``sha256:<hex>`` over the canonical JSON (sorted keys, no spaces) of
every other field. Loading checks every field: JSON integers only (no booleans, strings,
fractions, exponents or ``Infinity``), ranges, the phases the variant's table stores, the
invariants of a session, and the supervisor-side identity ``usable + Σreserved +
Σ(delivered − returned) = initial + injected − withdrawn`` (``withdrawn_uj``, a gateway's
returns upstream, may be absent: 0). A file that fails is refused naming the field; a
file whose checksum is missing or wrong (edited by hand, or version 1, which has none) only with
``accept_edited``, and the next save writes a fresh checksum.

The checksum guards against damage, not edits: anyone can recompute it. In authenticated mode
(``--auth``) the file also records the keys' ``epoch`` and carries ``mac``, a MAC over the same
canonical content under a key derived from the master key (``canergy.auth.state_key``). A file
kept under keys of another epoch is refused, whatever the flags; a MAC that is missing (stripped,
or the file written without ``--auth``) or wrong is refused unless ``accept_edited``, and so is a
sealed file loaded without a key. State files and their temporaries are created 0600.

A supervisor over several buses (``--bus``) keys its sessions ``bus/node`` (``can1/5``); its
file loads only with the same bus names, as one on a single bus loads only with its nodes.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

from canergy.auth.keys import EPOCH_MAX
from canergy.auth.state_key import StateSeal, claim
from canergy.bus_keys import node_name, parse_node_id, session_key
from canergy.core.state import SYNC_PHASES, Decision, Phase, Session, SupervisorState
from canergy.core.table import SupervisorTable
from canergy.core.variants import VARIANTS
from canergy.frozen import evolve
from canergy.live.atomic import write_atomic
from canergy.messages import (
    AMOUNT_MAX_MJ,
    COUNTER_BOUND,
    MAX_NODE,
    MIN_NODE,
    NONCE_BITS,
    QUANTUM_UJ,
    SEQ_BITS,
    counter_beyond,
)

ANSWERED_MAX = (1 << (NONCE_BITS + 1)) - 1
"""The last start answered (``resume_nonce``): its 16-bit nonce and, above it, whether it was a
SYNC's counts (``canergy.core.witnessed``)."""

JOIN_NONCE_MAX = (1 << NONCE_BITS) - 1
"""The last JOIN admitted (``join_nonce``): its 16-bit nonce."""

ANSWERED_BEHIND = 1 << (SEQ_BITS - 1)
"""How far below 0 the last start answered may be numbered (``resume_from``): its 16-bit q
widened next to C finds it up to 2^15 behind, below 0 while C is below 2^15 (a start no honest
node sends, found behind)."""

FORMAT = "canergy-supervisor-state"
VERSION = 2
"""2: with ``checksum``. Version 1 files (no checksum) load only with ``accept_edited``."""
READABLE_VERSIONS = (1, VERSION)
ENERGY_MAX_UJ = 2**63 - 1
"""Largest energy (and count) a field may hold: a signed 64-bit number of µJ."""
RESERVED_MAX_UJ = AMOUNT_MAX_MJ * QUANTUM_UJ
"""A reservation is one transaction's amount: at most what one frame carries."""
MAX_FILE_BYTES = 1 << 20
"""Far above any real state file (127 nodes take about 25 kB)."""
ACCEPT_EDITED = "--accept-edited-state"
SEAL_FIELDS = ("checksum", "mac")
"""Fields outside the canonical content: what guards it."""
TOP_OPTIONAL = (*SEAL_FIELDS, "epoch")

_TOP = ("format", "version", "variant", "initial_uj", "usable_uj", "injected_uj", "sessions")
_SESSION = (
    "phase",
    "tx",
    "reserved_uj",
    "delivered_uj",
    "decision",
    "returns_credited",
    "returned_uj",
)
_RESUME = ("resume_nonce", "resume_from", "resume_to", "join_nonce", "join_tx", "join_seq")
"""Witnessed rules: the last RESUME answered (its nonce, the node's debit number, the number
it voided), so that a copy re-sent after a restart gets the same answer, not a second void; and
the last JOIN admitted (its nonce, the k and C of its ADMIT), so that a copy gets the same ADMIT,
not a second admission. Each optional: a file written before holds none (0)."""
_DECIDED = (Phase.WAIT_CONFIRM, Phase.WAIT_STATUS)
"""Phases a session reaches only after sending its decision (COMMIT or ABORT)."""


class StateFileError(ValueError):
    """The state file is unreadable, fails its checks, or does not match the command line."""


@functools.cache
def stored_phase(table: SupervisorTable, phase: Phase) -> Phase:
    """``phase`` as the table's persistent record keeps it (hardened: ACKED as WAIT_ACK)."""
    record = table.persistent(Session(MIN_NODE, phase=phase))
    kept = record[0] if record else phase
    return kept if isinstance(kept, Phase) else phase


def stored_phases(table: SupervisorTable) -> tuple[Phase, ...]:
    """The phases a state file of this table may hold."""
    return tuple(dict.fromkeys(stored_phase(table, p) for p in table.phases))


def _as_read(value: object) -> str:
    """A number no field takes (``1e30``), encoded as its text: it can only fail the check."""
    if isinstance(value, _Number):
        return value.text
    raise TypeError(f"{type(value).__name__} is not JSON")


_CANONICAL = json.JSONEncoder(sort_keys=True, separators=(",", ":"), default=_as_read)
"""The checksum's encoding, made once (``json.dumps`` with options builds an encoder per
call)."""
_canonical = _CANONICAL.encode


def canonical_content(books: dict[str, Any]) -> bytes:
    """The canonical JSON of every field but ``checksum`` and ``mac``: what they guard."""
    return _canonical({k: v for k, v in books.items() if k not in SEAL_FIELDS}).encode()


def _sha256(content: bytes) -> str:
    return "sha256:" + hashlib.sha256(content).hexdigest()


def books_checksum(books: dict[str, Any]) -> str:
    """``sha256:<hex>`` over the books' canonical content."""
    return _sha256(canonical_content(books))


def sealed_text(books: dict[str, Any], seal: StateSeal | None) -> bytes:
    """A file's content: ``books`` (epoch included when sealed), its checksum and MAC."""
    head = {} if seal is None else {"epoch": seal.epoch}
    body = _canonical({**books, **head})
    return _with_seal(body, seal)


def _with_seal(body: str, seal: StateSeal | None) -> bytes:
    """``body`` (canonical JSON, ``epoch`` in it when sealed) with its checksum and MAC."""
    content = body.encode()
    tail = f',"checksum":"{_sha256(content)}"'
    if seal is not None:
        tail += f',"mac":"{seal.mac(content)}"'
    return content[:-1] + tail.encode() + b"}\n"


@dataclass(slots=True)
class _Kept:
    """How this process saves one state file (``keep_books``)."""

    seal: StateSeal | None
    claim: Callable[[], None] | None = None
    """Records the seal's key in its epochs record; run before the first save."""


_KEPT: dict[Path, _Kept] = {}
"""Per state file path: the service and a gateway's files save by path alone."""


def saves_seal(path: Path) -> StateSeal | None:
    """The seal of a save of ``path`` (``keep_books``; None: none); the first save records the
    key's claim before it writes."""
    kept = _KEPT.get(path)
    if kept is None:
        return None
    if kept.claim is not None:
        kept.claim()
        kept.claim = None
    return kept.seal


def write_private(path: Path, data: bytes, *, fsync: bool = True) -> None:
    """Replace ``path`` atomically with a file only its owner may read or write (0600 from
    the first byte, whatever the umask)."""
    write_atomic(path, data, fsync=fsync, mode=0o600)


def session_json(table: SupervisorTable | None, s: Session) -> dict[str, Any]:
    """One session as saved (``table``: the variant's, to store phases as its record does;
    the witnessed rules' also the last RESUME answered and the last JOIN admitted)."""
    saved = {
        "phase": (s.phase if table is None else stored_phase(table, s.phase)).name,
        "tx": s.tx,
        "reserved_uj": s.reserved,
        "delivered_uj": s.delivered,
        "decision": s.decision.name,
        "returns_credited": s.returns_credited,
        "returned_uj": s.returned,
    }
    if table is not None and _takes_resume(table):
        saved |= {
            "resume_nonce": s.resume_nonce,
            "resume_from": s.resume_from,
            "resume_to": s.resume_to,
            "join_nonce": s.join_nonce,
            "join_tx": s.join_tx,
            "join_seq": s.join_seq,
        }
    return saved


def _takes_resume(table: SupervisorTable) -> bool:
    """The table answers RESUME (witnessed rules): its sessions keep the last one answered."""
    return table.variant == "witnessed"


def _books_head(state: SupervisorState, variant: str) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "version": VERSION,
        "variant": variant,
        "initial_uj": state.initial,
        "usable_uj": state.usable,
        "injected_uj": state.injected,
        "withdrawn_uj": state.withdrawn,
    }


def _table(variant: str) -> SupervisorTable | None:
    known = VARIANTS.get(variant)
    return known.supervisor if known is not None else None


def state_json(state: SupervisorState, variant: str, buses: Sequence[str] = ()) -> dict[str, Any]:
    """The books as saved, without the checksum; ``buses``: the names of a supervisor's buses
    (sessions keyed ``bus/node``), none on a single bus (keyed by node id)."""
    table = _table(variant)
    sessions = {str(node_name(buses, s.node)): session_json(table, s) for s in state.sessions}
    return {**_books_head(state, variant), "sessions": sessions}


class BooksWriter:
    """Saves one supervisor's books to ``path``, atomically, as often as they change.

    The file is the books' canonical JSON (what ``books_checksum`` hashes) with the checksum
    (and with ``seal`` the MAC) added last, so each save builds the JSON once; and each
    session's JSON is kept until that session changes (a step changes one), so a save of 127
    nodes encodes one session, not 127. ``seal``: by default the one ``keep_books`` set.
    """

    def __init__(
        self,
        path: Path,
        variant: str,
        *,
        fsync: bool = True,
        buses: Sequence[str] = (),
        seal: StateSeal | None = None,
    ) -> None:
        self.path = path
        self.variant = variant
        self.fsync = fsync
        self.buses = tuple(buses)
        self.seal = seal
        """None: the one ``keep_books`` set for ``path``, if any."""
        self._table = _table(variant)
        self._sessions: dict[int, tuple[Session, str]] = {}
        """Per session key: the session last encoded and its ``"name":{...}`` text."""
        self._order: tuple[tuple[int, ...], list[int]] = ((), [])
        """The session keys as last seen, and the same keys in the order of their names."""

    def text(self, state: SupervisorState, seal: StateSeal | None = None) -> bytes:
        """The file's content for ``state`` (checksum, and with ``seal`` the MAC)."""
        sessions = {s.node: s for s in state.sessions}
        keys = tuple(sessions)
        if self._order[0] != keys:
            by_name = sorted(keys, key=lambda k: str(node_name(self.buses, k)))
            self._order = (keys, by_name)
        parts = []
        for key in self._order[1]:
            s = sessions[key]
            kept = self._sessions.get(key)
            if kept is None or kept[0] is not s:
                name = _canonical(str(node_name(self.buses, key)))
                entry = _canonical(session_json(self._table, s))
                kept = self._sessions[key] = (s, f"{name}:{entry}")
            parts.append(kept[1])
        fields = {k: _canonical(v) for k, v in _books_head(state, self.variant).items()}
        if seal is not None:
            fields["epoch"] = _canonical(seal.epoch)
        fields["sessions"] = "{" + ",".join(parts) + "}"
        body = "{" + ",".join(f"{_canonical(k)}:{fields[k]}" for k in sorted(fields)) + "}"
        return _with_seal(body, seal)

    def save(self, state: SupervisorState) -> None:
        seal = self.seal if self.seal is not None else saves_seal(self.path)
        write_private(self.path, self.text(state, seal), fsync=self.fsync)


def save_state(
    path: Path,
    state: SupervisorState,
    variant: str,
    *,
    fsync: bool = True,
    buses: Sequence[str] = (),
    seal: StateSeal | None = None,
) -> None:
    """Save ``state`` once (a running supervisor keeps a ``BooksWriter``)."""
    BooksWriter(path, variant, fsync=fsync, buses=buses, seal=seal).save(state)


def books_nodes(path: Path | None) -> tuple[int, ...]:
    """The node ids a one-bus state file holds books for (none when it cannot be read, or for a
    bus/node key: ``load_state`` then says what is wrong). ``canergy grant`` carries them all, so
    that the books of nodes it does not grant to are kept as they are."""
    if path is None:
        return ()
    try:
        sessions = json.loads(path.read_text())["sessions"]
    except (OSError, ValueError, KeyError, TypeError):
        return ()
    nodes = []
    for key in sessions if isinstance(sessions, dict) else ():
        if isinstance(key, str) and key.isdigit() and MIN_NODE <= int(key) <= MAX_NODE:
            nodes.append(int(key))
    return tuple(sorted(nodes))


def load_state(
    path: Path,
    variant: str,
    nodes: tuple[int, ...],
    *,
    buses: Sequence[str] = (),
    accept_edited: bool = False,
    on_edited: Callable[[str], None] | None = None,
    seal: StateSeal | None = None,
) -> SupervisorState:
    """Read and check ``path``; the file's nodes must all be in ``nodes`` (new nodes get fresh
    sessions). ``buses``: a supervisor over several buses, its bus names in order (``nodes`` are
    then session keys); the file's buses must all be among them. ``seal``: authenticated mode,
    the file's epoch must be the seal's. A missing or wrong checksum or MAC is refused unless
    ``accept_edited``; then the file is taken when it passes every other check and
    ``on_edited`` hears why it needed the flag."""
    data = read_json(path)
    state = FieldChecker(path, buses).books(data, variant)
    legacy = data["version"] if data["version"] != VERSION else None
    check_guards(path, data, seal, accept_edited, on_edited, legacy=legacy)
    sessions = {s.node: s for s in state.sessions}
    extra = sorted(set(sessions) - set(nodes))
    if extra and buses:
        names = ", ".join(str(node_name(buses, key)) for key in extra)
        raise StateFileError(
            f"{path} holds open books for node(s) {names} not on the command line; add them "
            "to their --bus"
        )
    if extra:
        raise StateFileError(
            f"{path} holds open books for node(s) {extra} not in --nodes; add them to --nodes"
        )
    merged = tuple(sessions.get(n, Session(n)) for n in sorted(nodes))
    return evolve(state, sessions=merged)


def keep_books(path: Path, seal: StateSeal | None, key_path: Path | None, *, fresh: bool) -> None:
    """Seal every later save of ``path`` in this process (None: the checksum only). With a seal,
    its key is checked against the epochs record beside ``key_path`` now (``fresh``, new books:
    refused if it kept books) and recorded there before the first save."""
    pending = None if seal is None or key_path is None else claim(key_path, seal, path, fresh=fresh)
    _KEPT[path] = _Kept(seal, pending)


@dataclass(frozen=True, slots=True)
class _Number:
    """A JSON number that is no acceptable integer (``1e30``, ``0.5``, ``Infinity``, 5000
    digits), kept so that the check of its field can name the field."""

    text: str
    why: str


def _fraction(text: str) -> _Number:
    return _Number(text, "is not an integer")


def _constant(text: str) -> _Number:
    return _Number(text, "is not a number")


def _integer(text: str) -> int | _Number:
    if len(text) > 20:  # beyond any 64-bit value; int() would refuse 4300 digits anyway
        return _Number(f"{text[:12]}...", f"has {len(text.lstrip('-'))} digits: out of range")
    return int(text)


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise ValueError(f"duplicate key {key[:40]!r}")
        obj[key] = value
    return obj


def read_json(path: Path) -> Any:
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise StateFileError(f"{path}: unreadable state file ({exc})") from exc
    if len(raw) > MAX_FILE_BYTES:
        raise StateFileError(f"{path}: unreadable state file (over {MAX_FILE_BYTES} bytes)")
    try:
        return json.loads(
            raw.decode("utf-8"),
            parse_float=_fraction,
            parse_constant=_constant,
            parse_int=_integer,
            object_pairs_hook=_no_duplicates,
        )
    except RecursionError:
        raise StateFileError(f"{path}: unreadable state file (nested too deeply)") from None
    except ValueError as exc:  # bad JSON or UTF-8, a duplicate key
        raise StateFileError(f"{path}: unreadable state file ({exc})") from exc


def _text(value: object) -> str:
    """A scalar JSON value as a short one-line text."""
    if isinstance(value, _Number):
        return value.text
    if isinstance(value, str | int | float | bool) or value is None:
        return json.dumps(value[:40] if isinstance(value, str) else value)
    return "an object" if isinstance(value, dict) else "a list"


def _shown(value: object) -> str:
    """A JSON value as a short one-line text, with what kind of value it is."""
    if isinstance(value, _Number):
        return f"{value.text} {value.why}"
    if isinstance(value, bool) or value is None:
        return f"{json.dumps(value)} is not an integer"
    if isinstance(value, str):
        text = json.dumps(value[:40] + ("..." if len(value) > 40 else ""))
        return f"{text} is a string, not an integer"
    return f"{'an object' if isinstance(value, dict) else 'a list'} is not an integer"


@dataclass(frozen=True, slots=True)
class _Problem:
    """Why a file's guard fails: the field, what is wrong, what may fix it besides the flag."""

    field: str
    why: str
    hint: str = ""


def check_guards(
    path: Path,
    data: dict[str, Any],
    seal: StateSeal | None,
    accept_edited: bool,
    on_edited: Callable[[str], None] | None,
    *,
    legacy: int | None = None,
) -> None:
    """Refuse books of another epoch than ``seal``'s, whatever the flag; then a checksum or MAC
    that is missing or wrong unless ``accept_edited`` (``on_edited`` hears why the flag was
    needed). ``legacy``: the version of a file written before checksums."""
    _check_epoch(path, data, seal)
    problem = _sum_problem(data, legacy) or _seal_problem(data, seal)
    if problem is None:
        return
    if not accept_edited:
        raise StateFileError(
            f"{path}: {problem.field}: {problem.why}; {problem.hint}check the books, then pass "
            f"{ACCEPT_EDITED} to take it as it is"
        )
    if on_edited is not None:
        fresh = "a fresh checksum" + (" and MAC" if seal is not None else "")
        on_edited(
            f"{path}: {problem.why}; taken as it is ({ACCEPT_EDITED}), the next save writes {fresh}"
        )


def _check_epoch(path: Path, data: dict[str, Any], seal: StateSeal | None) -> None:
    if "epoch" not in data:
        return
    found = FieldChecker(path).integer(data, "", "epoch", EPOCH_MAX)
    if seal is not None and found != seal.epoch:
        raise StateFileError(
            f"{path}: epoch: the books were begun under keys of epoch {found}, but --auth gives "
            f"keys of epoch {seal.epoch}; run with the master key of epoch {found}. Books keep "
            "the epoch they began with: keys of a new epoch need a new state file, and a state "
            "file started again needs keys of a new epoch, or frames of the old books verify "
            "again"
        )


def _sum_problem(data: dict[str, Any], legacy: int | None) -> _Problem | None:
    found = data.get("checksum")
    if legacy is not None:
        why = f"a version {legacy} file carries no checksum"
    elif found is None:
        why = "no checksum"
    elif found != books_checksum(data):
        why = "the checksum does not match the books"
    else:
        return None
    return _Problem("checksum", f"{why} (edited by hand?)")


def _seal_problem(data: dict[str, Any], seal: StateSeal | None) -> _Problem | None:
    """A MAC the key does not check: missing, wrong, or no key for a sealed file."""
    found = data.get("mac")
    if seal is None:
        if found is None and "epoch" not in data:
            return None
        return _Problem(
            "mac",
            "sealed in authenticated mode, and without its master key (--auth) the MAC cannot "
            "be checked",
            "run with that key, or ",
        )
    if found is None or "epoch" not in data:
        why = "no MAC (stripped, or written without --auth?)"
    elif not seal.matches(canonical_content(data), found):
        why = "the MAC does not match the books (edited, or sealed with another master key?)"
    else:
        return None
    return _Problem("mac", why)


def _at(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


class FieldChecker:
    """Checks the parsed file field by field; the first failure is refused, naming the field."""

    def __init__(self, path: Path, buses: Sequence[str] = ()) -> None:
        self.path = path
        self.buses = tuple(buses)
        """Bus names: sessions are keyed ``bus/node``; none: by node id."""

    def refuse(self, field: str, why: str) -> NoReturn:
        raise StateFileError(f"{self.path}: {field}: {why}")

    def fields(
        self, obj: object, where: str, names: Iterable[str], optional: tuple[str, ...] = ()
    ) -> dict[str, Any]:
        if not isinstance(obj, dict):
            self.refuse(where or "file", "not a JSON object")
        names = tuple(names)
        for key in obj:
            if key not in names and key not in optional:
                self.refuse(_at(where, key[:40]), "unknown field")
        for name in names:
            if name not in obj:
                self.refuse(_at(where, name), "missing")
        return obj

    def integer(
        self, obj: dict[str, Any], where: str, name: str, high: int = ENERGY_MAX_UJ, low: int = 0
    ) -> int:
        value, field = obj[name], _at(where, name)
        if type(value) is not int:
            self.refuse(field, _shown(value))
        if value < low:
            owes = f"{value} is below {low}, the most this field may owe"
            self.refuse(field, owes if low else f"{value} is negative")
        if value > high:
            self.refuse(field, f"{value} is above {high}, the most this field may hold")
        return value

    def counter(self, obj: dict[str, Any], where: str, name: str) -> int:
        """A transaction or return number: below ``COUNTER_BOUND``, the bound the proof
        assumes (``canergy prove``, assumption 4)."""
        value = self.integer(obj, where, name)
        if value >= COUNTER_BOUND:
            self.refuse(_at(where, name), counter_beyond(value))
        return value

    def answered_from(self, obj: dict[str, Any], where: str) -> int:
        """The debit number of the last start answered (``resume_from``): a counter, or below 0
        by at most ``ANSWERED_BEHIND`` (a start found behind early in the node's life)."""
        return self.integer(obj, where, "resume_from", COUNTER_BOUND - 1, -ANSWERED_BEHIND)

    def last_join(
        self, obj: dict[str, Any], where: str, tx: int, returns_credited: int
    ) -> tuple[int, int, int]:
        """The last JOIN admitted (witnessed rules; absent: none): its nonce, and the k and C of
        its ADMIT, neither above the session's own (tx and C never go back)."""
        nonce = self.integer(obj, where, "join_nonce", JOIN_NONCE_MAX) if "join_nonce" in obj else 0
        k = self.counter(obj, where, "join_tx") if "join_tx" in obj else 0
        c = self.counter(obj, where, "join_seq") if "join_seq" in obj else 0
        for name, value, own, limit in (
            ("join_tx", k, "tx", tx),
            ("join_seq", c, "returns_credited", returns_credited),
        ):
            if value > limit:
                self.refuse(_at(where, name), f"{value}: above {own} {limit}")
        return nonce, k, c

    def name(self, obj: dict[str, Any], where: str, name: str, choices: Iterable[str]) -> str:
        value, allowed = obj[name], tuple(choices)
        if value not in allowed:  # also every non-string
            self.refuse(_at(where, name), f"{_text(value)} is not one of {', '.join(allowed)}")
        assert isinstance(value, str)
        return value

    def books(self, data: object, variant: str) -> SupervisorState:
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise StateFileError(f"{self.path}: not a {FORMAT} file")
        version = data.get("version")
        if type(version) is not int or version not in READABLE_VERSIONS:
            readable = " or ".join(map(str, READABLE_VERSIONS))
            self.refuse(
                "version", f"{_text(version)} is not a version this canergy reads ({readable})"
            )
        if data.get("variant") != variant:
            raise StateFileError(
                f"{self.path}: written by variant {_text(data.get('variant'))}, not {variant!r}"
            )
        if variant not in VARIANTS:
            self.refuse("variant", f"unknown variant {variant!r}")
        table = VARIANTS[variant].supervisor
        self.fields(data, "", _TOP, optional=(*TOP_OPTIONAL, "withdrawn_uj"))
        initial = self.integer(data, "", "initial_uj")
        debt = any(phase in SYNC_PHASES for phase, _ in table.cells)  # books taken at a start
        usable = self.integer(data, "", "usable_uj", low=-ENERGY_MAX_UJ if debt else 0)
        injected = self.integer(data, "", "injected_uj")
        withdrawn = self.integer(data, "", "withdrawn_uj") if "withdrawn_uj" in data else 0
        raw_sessions = data["sessions"]  # its keys are node ids, checked one by one
        if not isinstance(raw_sessions, dict):
            self.refuse("sessions", "not a JSON object")
        sessions = tuple(
            self.session(self.node(key), value, table)
            for key, value in sorted(raw_sessions.items(), key=lambda kv: self.node(kv[0]))
        )
        reserved = sum(s.reserved for s in sessions)
        out_net = sum(s.delivered - s.returned for s in sessions)
        if usable + reserved + out_net != initial + injected - withdrawn:
            self.refuse(
                "usable_uj",
                f"the books do not balance: usable + reserved + (delivered - returned) = "
                f"{usable + reserved + out_net} µJ, initial + injected - withdrawn = "
                f"{initial + injected - withdrawn} µJ",
            )
        return SupervisorState(initial, usable, injected, sessions, withdrawn)

    def node(self, key: str) -> int:
        """The session key of a ``sessions`` key: a node id, or with bus names ``bus/node``."""
        where = f"sessions.{key[:40]}"
        bus, sep, text = key.rpartition("/")
        node = parse_node_id(text)
        if not self.buses and sep:
            self.refuse(
                where,
                "a bus/node key: written by a supervisor over several buses; run it with the "
                "same --bus options",
            )
        if self.buses and not sep:
            self.refuse(
                where,
                "a node id without its bus: written by a supervisor on one bus (--nodes); with "
                "--bus the books are keyed bus/node",
            )
        if node is None:
            self.refuse(where, f"not a node id ({MIN_NODE}-{MAX_NODE})")
        if not self.buses:
            return node
        if bus not in self.buses:
            self.refuse(
                where,
                f"bus {bus[:40]!r} is not on the command line (--bus {', '.join(self.buses)}); "
                "give every bus the file holds books for",
            )
        return session_key(self.buses.index(bus), node)

    def session(self, node: int, raw: object, table: SupervisorTable) -> Session:
        where = f"sessions.{node_name(self.buses, node)}"
        resumes = _takes_resume(table)
        v = self.fields(raw, where, _SESSION, optional=_RESUME if resumes else ())
        phase = Phase[self.name(v, where, "phase", (p.name for p in stored_phases(table)))]
        tx = self.counter(v, where, "tx")
        reserved = self.integer(v, where, "reserved_uj", RESERVED_MAX_UJ)
        delivered = self.integer(v, where, "delivered_uj")
        decision = Decision[self.name(v, where, "decision", (d.name for d in Decision))]
        returns_credited = self.counter(v, where, "returns_credited")
        returned = self.integer(v, where, "returned_uj")
        if phase is Phase.IDLE and reserved:
            self.refuse(f"{where}.reserved_uj", f"{reserved} µJ reserved while IDLE")
        if phase is not Phase.IDLE and not reserved:
            self.refuse(f"{where}.reserved_uj", f"nothing reserved in {phase.name}")
        if reserved % QUANTUM_UJ:
            self.refuse(f"{where}.reserved_uj", f"{reserved} µJ is not a whole number of mJ")
        if phase is not Phase.IDLE and tx == 0:
            self.refuse(f"{where}.tx", f"0 in {phase.name}: an open transaction is numbered")
        decided = phase in _DECIDED
        if decided == (decision is Decision.NONE):
            why = "no decision" if decided else f"decision {decision.name}"
            self.refuse(f"{where}.decision", f"{why} in {phase.name}")
        nonce, start, void = (
            (self.integer(v, where, "resume_nonce", ANSWERED_MAX) if "resume_nonce" in v else 0),
            (self.answered_from(v, where) if "resume_from" in v else 0),
            (self.counter(v, where, "resume_to") if "resume_to" in v else 0),
        )
        if resumes and void > returns_credited:
            self.refuse(f"{where}.resume_to", f"{void}: above returns_credited {returns_credited}")
        join_nonce, join_tx, join_seq = self.last_join(v, where, tx, returns_credited)
        return Session(
            node,
            phase,
            tx,
            reserved,
            delivered,
            decision,
            returns_credited,
            returned,
            resume_nonce=nonce,
            resume_from=start,
            resume_to=void,
            join_nonce=join_nonce,
            join_tx=join_tx,
            join_seq=join_seq,
        )
