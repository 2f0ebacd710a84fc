"""The supervisor's state file is checked on load (issue 13): types, ranges, the variant's
phases, session invariants, the books' identity and a checksum against silent edits."""

from __future__ import annotations

import json
import re
import uuid
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.cli import grant as grant_cli
from canergy.cli import main
from canergy.cli import supervisor as supervisor_cli
from canergy.core import witnessed as W
from canergy.core.state import Decision, Phase, Session, SupervisorState
from canergy.core.timing import Timing
from canergy.live.supervisor.state_file import (
    BooksWriter,
    StateFileError,
    books_checksum,
    load_state,
    save_state,
    state_json,
)
from canergy.messages import COUNTER_BOUND, Debit

J = 1_000_000
RAW = "@@raw@@"
"""Stands for a JSON token that ``json.dumps`` would never write (``1e30``, ``Infinity``)."""


def _state() -> SupervisorState:
    """Node 1 idle with history, node 3 waiting for its confirmation: the books balance."""
    sessions = (
        Session(1, Phase.IDLE, 4, 0, 3 * J, Decision.NONE, 2, 200_000),
        Session(3, Phase.WAIT_CONFIRM, 9, 500_000, J, Decision.COMMIT, 0, 0),
    )
    return SupervisorState(10 * J, 10 * J - 3 * J + 200_000 - 500_000 - J, 0, sessions)


def _books(tmp_path: Path, variant: str = "hardened") -> dict[str, Any]:
    path = tmp_path / "saved.json"
    save_state(path, _state(), variant, fsync=False)
    books: dict[str, Any] = json.loads(path.read_text())
    return books


def _write(path: Path, books: dict[str, Any], raw: str | None = None, *, seal: bool = True) -> None:
    """Write ``books`` with a checksum that matches them (``seal``), so only the field under
    test is wrong; ``raw`` replaces the value ``RAW`` as it stands in the text."""
    books = dict(books)
    books.pop("checksum", None)
    if seal:
        books["checksum"] = books_checksum(books)
    text = json.dumps(books)
    if raw is not None:
        text = text.replace(json.dumps(RAW), raw)
    path.write_text(text)


def _set(books: dict[str, Any], field: str, value: object) -> dict[str, Any]:
    """A deep copy of ``books`` with ``field`` (dotted, as in the error messages) set."""
    books = json.loads(json.dumps(books))
    *parents, last = field.split(".")
    target = books
    for part in parents:
        target = target[part]
    target[last] = value
    return books


def _load(path: Path, variant: str = "hardened", **kw: Any) -> SupervisorState:
    return load_state(path, variant, (1, 3), **kw)


def test_a_saved_file_loads_as_it_was_saved(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    save_state(path, _state(), "hardened", fsync=False)
    assert json.loads(path.read_text())["checksum"].startswith("sha256:")
    assert _load(path) == _state()


def test_the_checksum_covers_the_books_not_the_layout(tmp_path: Path) -> None:
    """Pretty-printing the file changes no value and keeps it loadable without the flag."""
    path = tmp_path / "s.json"
    save_state(path, _state(), "paper", fsync=False)
    path.write_text(json.dumps(json.loads(path.read_text()), indent=4))
    assert _load(path, "paper") == _state()


# A wrong value in each place the issue names, as (field, value, expected words).
REFUSED_VALUES = [
    ("usable_uj", 8_000_000, "the books do not balance"),  # hand-raised
    ("usable_uj", -1, "-1 is negative"),
    ("usable_uj", "7000000", '"7000000" is a string'),
    ("usable_uj", True, "true is not an integer"),
    ("usable_uj", None, "null is not an integer"),
    ("initial_uj", [1], "a list is not an integer"),
    ("injected_uj", 2**63, f"{2**63} is above {2**63 - 1}"),
    ("sessions.1.tx", -3, "-3 is negative"),
    ("sessions.1.returns_credited", -1, "-1 is negative"),
    ("sessions.1.delivered_uj", 2**64, "is above"),
    ("sessions.3.phase", "WAIT_STATUS", '"WAIT_STATUS" is not one of IDLE, WAIT_ACK, WAIT_CONFIRM'),
    ("sessions.3.phase", "ACKED", "is not one of"),  # the hardened record keeps it as WAIT_ACK
    ("sessions.3.phase", "AWAIT_COMMAND", "is not one of"),  # a client's phase
    ("sessions.3.phase", 3, "3 is not one of"),
    ("sessions.3.decision", "MAYBE", "is not one of NONE, COMMIT, ABORT"),
    ("sessions.3.reserved_uj", 100_000 * J, "is above 65535000"),  # 100 kJ
    ("sessions.3.reserved_uj", 500_500, "not a whole number of mJ"),
    ("sessions.3.reserved_uj", 0, "nothing reserved in WAIT_CONFIRM"),
    ("sessions.1.reserved_uj", 500_000, "500000 µJ reserved while IDLE"),
    ("sessions.3.decision", "NONE", "no decision in WAIT_CONFIRM"),
    ("sessions.1.decision", "COMMIT", "decision COMMIT in IDLE"),
    ("sessions.3.tx", 0, "0 in WAIT_CONFIRM"),
    ("sessions.1.colour", "red", "unknown field"),
    ("extra", 1, "unknown field"),
    ("sessions.3", [], "not a JSON object"),
    ("sessions", [], "not a JSON object"),
]


@pytest.mark.parametrize(("field", "value", "why"), REFUSED_VALUES)
def test_a_wrong_field_is_refused_by_name(
    tmp_path: Path, field: str, value: object, why: str
) -> None:
    books = _books(tmp_path)
    if field == "sessions.1.reserved_uj":  # keep the books balanced: only the invariant fails
        books = _set(books, "usable_uj", books["usable_uj"] - 500_000)
    path = tmp_path / "s.json"
    _write(path, _set(books, field, value))
    with pytest.raises(StateFileError) as exc:
        _load(path)
    message = str(exc.value)
    assert message.startswith(f"{path}: "), message
    named = "usable_uj" if why == "the books do not balance" else field
    assert f": {named}:" in message or f": {named} " in message, message
    assert why in message, message
    assert "\n" not in message


@pytest.mark.parametrize(
    ("token", "why"),
    [
        ("1e30", "1e30 is not an integer"),
        ("7000000.0", "7000000.0 is not an integer"),
        ("1e400", "1e400 is not an integer"),
        ("Infinity", "Infinity is not a number"),
        ("-Infinity", "-Infinity is not a number"),
        ("NaN", "NaN is not a number"),
        ("1" + "0" * 5000, "has 5001 digits: out of range"),
    ],
)
def test_json_numbers_that_are_no_integers_are_refused(
    tmp_path: Path, token: str, why: str
) -> None:
    path = tmp_path / "s.json"
    _write(path, _set(_books(tmp_path), "sessions.3.reserved_uj", RAW), raw=token)
    with pytest.raises(StateFileError, match=f"sessions.3.reserved_uj: .*{why}"):
        _load(path)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ('{"format": "canergy-supervisor-state", "sessions": ' + "[" * 200_000, "nested too deep"),
        ('{"format": "canergy-supervisor-state", "format": "x"}', "duplicate key 'format'"),
        (b"\xff\xfe{}", "unreadable"),
        ("[]", "not a canergy-supervisor-state file"),
    ],
)
def test_a_file_that_is_no_state_file_is_refused(
    tmp_path: Path, text: str | bytes, why: str
) -> None:
    path = tmp_path / "s.json"
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    with pytest.raises(StateFileError, match=why):
        _load(path)


@pytest.mark.parametrize(
    ("key", "why"),
    [
        ("01", "not a node id"),
        ("0", "not a node id"),
        ("200", "not a node id"),
        ("x", "not a node id"),
    ],
)
def test_session_keys_are_node_ids(tmp_path: Path, key: str, why: str) -> None:
    books = _books(tmp_path)
    books["sessions"][key] = books["sessions"].pop("1")
    path = tmp_path / "s.json"
    _write(path, books)
    with pytest.raises(StateFileError, match=f"sessions.{key}: {why}"):
        _load(path)


def test_a_missing_field_is_named(tmp_path: Path) -> None:
    books = _books(tmp_path)
    del books["sessions"]["3"]["returned_uj"]
    path = tmp_path / "s.json"
    _write(path, books)
    with pytest.raises(StateFileError, match=re.escape("sessions.3.returned_uj: missing")):
        _load(path)


def test_the_paper_variant_keeps_its_own_phases(tmp_path: Path) -> None:
    books = _set(_books(tmp_path, "paper"), "sessions.3.phase", "WAIT_STATUS")
    path = tmp_path / "s.json"
    _write(path, books)
    assert _load(path, "paper").sessions[1].phase is Phase.WAIT_STATUS
    _write(path, _set(books, "sessions.3.phase", "AWAIT_SUPERVISOR"))
    with pytest.raises(StateFileError, match=r"sessions\.3\.phase: .* is not one of"):
        _load(path, "paper")


# -- the checksum ----------------------------------------------------------------------------


def _balanced_edit(tmp_path: Path) -> tuple[Path, dict[str, Any]]:
    """A hand edit that keeps every check but the checksum: 1 J more, initial and usable."""
    books = _books(tmp_path)
    edited = _set(
        _set(books, "initial_uj", books["initial_uj"] + J), "usable_uj", books["usable_uj"] + J
    )
    edited["checksum"] = books["checksum"]
    path = tmp_path / "s.json"
    path.write_text(json.dumps(edited))
    return path, edited


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ("edit", "the checksum does not match the books"),
        ("drop", "no checksum"),
        ("number", "the checksum does not match the books"),
        ("v1", "a version 1 file carries no checksum"),
    ],
)
def test_an_edited_file_needs_the_flag(tmp_path: Path, change: str, why: str) -> None:
    path, books = _balanced_edit(tmp_path)
    if change == "drop":
        del books["checksum"]
    elif change == "number":
        books["checksum"] = 12
    elif change == "v1":
        books = {k: v for k, v in _books(tmp_path).items() if k != "checksum"}
        books["version"] = 1
    path.write_text(json.dumps(books))
    with pytest.raises(StateFileError) as exc:
        _load(path)
    message = str(exc.value)
    assert f"{path}: checksum: {why}" in message
    assert "edited by hand?" in message and "--accept-edited-state" in message
    heard: list[str] = []
    state = _load(path, accept_edited=True, on_edited=heard.append)
    assert state.initial == books["initial_uj"] and state.usable == books["usable_uj"]
    assert len(heard) == 1 and why in heard[0]
    save_state(path, state, "hardened", fsync=False)  # the next save seals it again
    assert _load(path) == state


def test_the_flag_does_not_take_books_that_fail_a_check(tmp_path: Path) -> None:
    books = _set(_books(tmp_path), "usable_uj", 99 * J)
    path = tmp_path / "s.json"
    _write(path, books, seal=False)
    with pytest.raises(StateFileError, match="usable_uj: the books do not balance"):
        _load(path, accept_edited=True)


def test_an_unknown_version_is_refused_even_with_the_flag(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    _write(path, _set(_books(tmp_path), "version", 3))
    with pytest.raises(StateFileError, match="version: 3 is not a version this canergy reads"):
        _load(path, accept_edited=True)


# -- through the command line ----------------------------------------------------------------


@pytest.fixture
def started(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[dict[str, Any]]]:
    """Replace the supervisor's loop: each run starts, reports its status once and ends."""
    seen: list[dict[str, Any]] = []

    def serve(runtime: Any, service: Any, control: Any, **kw: Any) -> None:
        seen.append(service.status())

    monkeypatch.setattr(supervisor_cli, "serve_supervisor", serve)
    monkeypatch.setattr(grant_cli, "serve_supervisor", serve)
    yield seen


def _supervisor(state: Path, *extra: str) -> list[str]:
    bus = ["-i", "virtual", "-c", f"state-{uuid.uuid4().hex}"]
    return ["supervisor", *bus, "--nodes", "1-3", "--state", str(state), "--no-fsync", *extra]


RunMain = Callable[[list[str]], tuple[int, str]]


@pytest.fixture
def run(capsys: pytest.CaptureFixture[str]) -> RunMain:
    def run_main(argv: list[str]) -> tuple[int, str]:
        code = main(argv)
        return code, capsys.readouterr().err

    return run_main


def test_the_supervisor_refuses_an_edited_file_in_one_line(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    path, _ = _balanced_edit(tmp_path)
    before = path.read_bytes()
    code, err = run(_supervisor(path))
    assert code == 2 and not started
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert str(path) in err and "edited by hand?" in err and "--accept-edited-state" in err
    assert path.read_bytes() == before  # refused before anything was written

    code, err = run(_supervisor(path, "--accept-edited-state"))
    assert code == 0 and "warning" in err and "taken as it is" in err, err
    assert started[0]["initial_uj"] == 11 * J and started[0]["conservation"]["holds"]
    assert load_state(path, "hardened", (1, 2, 3)).initial == 11 * J  # sealed at start


@pytest.mark.parametrize(
    ("field", "raw", "words"),
    [
        (
            "sessions.3.reserved_uj",
            str(100_000 * J),
            "sessions.3.reserved_uj: 100000000000 is above",
        ),
        ("usable_uj", "Infinity", "usable_uj: Infinity is not a number"),
        ("usable_uj", "1e400", "usable_uj: 1e400 is not an integer"),
    ],
)
def test_the_supervisor_names_the_field_in_one_line(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]], field: str, raw: str, words: str
) -> None:
    path = tmp_path / "s.json"
    _write(path, _set(_books(tmp_path), field, RAW), raw=raw)
    code, err = run(_supervisor(path, "--accept-edited-state"))
    assert code == 2 and not started
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{path}: {words}" in err, err


# -- the running supervisor's writer ---------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(
        st.tuples(st.sampled_from((1, 2, 10, 100, 127)), st.integers(0, 50), st.integers(0, 9)),
        min_size=1,
        max_size=12,
    ),
    buses=st.sampled_from(((), ("can0", "can1"), ("z", "a!"))),
)
def test_the_writer_saves_what_the_reference_encoding_saves(
    tmp_path_factory: pytest.TempPathFactory,
    steps: list[tuple[int, int, int]],
    buses: tuple[str, ...],
) -> None:
    """Save after save, one session changed each time (its kept text must not go stale): the
    file holds exactly ``state_json`` plus the checksum ``load_state`` checks."""
    path = tmp_path_factory.mktemp("books") / "s.json"
    keys = (1, 2, 10, 100, 127) if not buses else (1, 2, 10, 1 << 8 | 100, 1 << 8 | 127)
    sessions = {k: Session(k) for k in keys}
    writer = BooksWriter(path, "hardened", fsync=False, buses=buses)
    for node, tx, returns in steps:
        key = keys[(1, 2, 10, 100, 127).index(node)]
        sessions[key] = Session(key, Phase.IDLE, tx, 0, tx * J, Decision.NONE, returns, returns)
        delivered = sum(s.delivered - s.returned for s in sessions.values())
        state = SupervisorState(10**9, 10**9 - delivered, 0, tuple(sessions.values()))
        writer.save(state)
        books = json.loads(path.read_text())
        checksum = books.pop("checksum")
        assert books == state_json(state, "hardened", buses)
        assert checksum == books_checksum(books)
        assert load_state(path, "hardened", keys, buses=buses) == state


def _witnessed_after_a_start(usable: int) -> SupervisorState:
    """Witnessed books after a start the node confirmed with its counts (the last answer keeps
    bit 16 over the SYNC's nonce) and, with ``usable`` below 0, a debt its books brought; node
    1 admitted after a JOIN at tx 65 (C 8) and gone on since."""
    joined = {"join_nonce": 0xFFFF, "join_tx": 65, "join_seq": 8}
    sessions = (
        Session(1, Phase.IDLE, 70, 0, 3 * J - usable, Decision.NONE, 9, 0, **joined),
        Session(3, resume_nonce=1 << 16 | 0xBEEF, resume_from=0, resume_to=1, returns_credited=1),
    )
    return SupervisorState(3 * J, usable, 0, sessions)


@pytest.mark.parametrize("usable", [2 * J, -800_000], ids=["in credit", "in debt"])
def test_a_witnessed_supervisor_starts_again_from_the_books_it_wrote(
    tmp_path: Path, usable: int
) -> None:
    """What a witnessed start writes (a SYNC's counts answered, a debt) loads again: before,
    the loader refused both, so a second start after a confirmed SYNC failed."""
    path = tmp_path / "s.json"
    save_state(path, _witnessed_after_a_start(usable), "witnessed", fsync=False)
    assert _load(path, "witnessed") == _witnessed_after_a_start(usable)


def test_witnessed_books_written_before_the_last_join_was_kept_load_with_none(
    tmp_path: Path,
) -> None:
    """A file without ``join_*`` (written before they were kept) loads with no JOIN admitted
    (0): the next copy of that JOIN is admitted afresh, as the rules before did."""
    path = tmp_path / "s.json"
    save_state(path, _witnessed_after_a_start(2 * J), "witnessed", fsync=False)
    books = json.loads(path.read_text())
    for session in books["sessions"].values():
        for name in ("join_nonce", "join_tx", "join_seq"):
            del session[name]
    _write(path, books)
    sessions = tuple(
        replace(s, join_nonce=0, join_tx=0, join_seq=0)
        for s in _witnessed_after_a_start(2 * J).sessions
    )
    assert _load(path, "witnessed").sessions == sessions


@pytest.mark.parametrize("flags", [Debit.START, Debit.START | Debit.SYNC], ids=["resume", "counts"])
@pytest.mark.parametrize("q", [0xFFF0, 0x800A])
def test_a_start_numbered_far_behind_leaves_books_that_load_again(
    tmp_path: Path, flags: int, q: int
) -> None:
    """A RESUME or counts whose 16-bit q widens below 0 next to C (anyone can send one without
    a key; C below 2^15, as early in a node's life): the rules find it behind and remember
    its q as answered (resume_from below 0, as the compiled core gives it back too). Before,
    the loader refused that ('resume_from: -16 is negative'): the supervisor wrote books its
    next start refused."""
    s = Session(1, tx=70, witness=70, returns_credited=9, delivered=3 * J)
    ltx = 70 if flags & Debit.SYNC else 0  # counts of another nonce: taken with an ltx at tx
    step = W.SUPERVISOR.step(Timing(), s, Debit(1, 0x0505, flags, q, ltx), 0)
    assert step.session.resume_from < 0
    books = replace(step.session, witness=0)  # W is not in the books (a start SYNCs)
    state = SupervisorState(3 * J, 0, 0, (books, Session(3)))
    path = tmp_path / "s.json"
    save_state(path, state, "witnessed", fsync=False)
    assert _load(path, "witnessed") == state


@pytest.mark.parametrize(
    ("variant", "field", "value", "why"),
    [
        ("hardened", "usable_uj", -800_000, "-800000 is negative"),  # no rule there owes
        ("witnessed", "usable_uj", -(2**63), "is below"),
        ("witnessed", "sessions.3.resume_nonce", 1 << 17, "is above 131071"),
        ("witnessed", "sessions.1.join_nonce", 1 << 16, "is above 65535"),
        ("witnessed", "sessions.1.join_tx", 71, "join_tx: 71: above tx 70"),
        ("witnessed", "sessions.1.join_seq", 10, "join_seq: 10: above returns_credited 9"),
        ("witnessed", "sessions.1.join_seq", COUNTER_BOUND, "join_seq"),
    ],
)
def test_what_a_witnessed_start_writes_is_bounded_and_refused_elsewhere(
    tmp_path: Path, variant: str, field: str, value: int, why: str
) -> None:
    path = tmp_path / "s.json"
    save_state(path, _witnessed_after_a_start(-800_000), "witnessed", fsync=False)
    books = json.loads(path.read_text())
    books["variant"] = variant
    if variant == "hardened":
        for session in books["sessions"].values():
            for name in ("resume_nonce", "resume_from", "resume_to"):
                session.pop(name, None)
            for name in ("join_nonce", "join_tx", "join_seq"):
                session.pop(name, None)
    _write(path, _set(books, field, value))
    with pytest.raises(StateFileError, match=why):
        _load(path, variant)
