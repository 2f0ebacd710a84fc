"""A supervisor's state file put back to an older copy (a backup, a VM snapshot) after grants,
on the live stack: `canergy supervisor` as users run it and the emulated node on python-can's
virtual bus (issue 40, item 5). Under the hardened rules the restored books count in Us again
what the node received after the copy and grant it once more; under ``--variant witnessed`` the
restarted supervisor sends SYNC, grants nothing until the node has answered with its books (the
wait is in the status and on stderr), and Gs moves up to the node's Rc: nothing is created.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest
from test_live_old_copy import Bench, bench, held, released, wait

from canergy.auth.frames import FrameAuth, Layout, expected_freshness
from canergy.ccore.supervisor import make_supervisor
from canergy.cli import main
from canergy.codec import Codec
from canergy.core import Timing
from canergy.core.state import Session, SupervisorState
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.state_file import load_state
from canergy.messages import Ack, Admit, Committed, Debit, Direction, Intention, Telemetry
from canergy.units import UJ_PER_J

NODE = 1


CORES = ("python", "c")
"""``canergy supervisor --core``: the rules in Python, or firmware/'s C supervisor role."""
KEYS = [None, *Layout]
KEY_IDS = ["no key", "auth classic", "auth fd"]


def restored_books(
    tmp: Path, variant: str, auth: Layout | None, core: str = "python", again: tuple[str, ...] = ()
) -> tuple[Bench, int, str]:
    """The supervisor grants; its state file is copied; it grants 2 J more; the node and the
    supervisor stop; the copy is put back and the supervisor starts from it (with the flags
    ``again``), the node off. Returns the new supervisor, what the node's first life's actuator
    used, and the copy (what the first life still held is in its record, which the second life
    starts from)."""
    b = bench(tmp, variant, auth, core=core)
    node, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("committed", 0) >= 2)
        copy = (tmp / "s.json").read_text()
        at_copy = b.node_status()["committed_uj"]
        wait(lambda: b.node_status()["committed_uj"] >= at_copy + 2 * UJ_PER_J)
    finally:
        loop.halt()
    b.stop_supervisor()
    first = node.actuator.drawn_uj
    (tmp / "s.json").write_text(copy)
    (tmp / "status.json").unlink()
    return bench(tmp, variant, auth, b.channel, core, again), first, copy


SAID_APART = ("core", "frame_path")
"""Status keys in which the two cores differ by design."""


@pytest.mark.parametrize("auth", KEYS, ids=KEY_IDS)
@pytest.mark.parametrize("core", CORES)
def test_an_older_copy_of_the_supervisors_books_creates_nothing_under_witnessed(
    tmp_path: Path, core: str, auth: Layout | None, caplog: pytest.LogCaptureFixture
) -> None:
    b, first, _ = restored_books(tmp_path, "witnessed", auth, core)
    wait(lambda: b.status().get("waiting_for_books") == [NODE])
    waiting = b.status()
    assert waiting["core"] == core
    assert "no grant to any node until node(s) 1" in waiting["waiting_why"]
    assert waiting["granted_this_run_uj"] == 0
    node, loop = b.start_node()  # the node's second life, from its own (current) record
    try:
        wait(lambda: b.node_status().get("synced") == 1)
        assert b.status()["waiting_for_books"] == []
        wait(lambda: b.node_status()["committed"] >= 3)  # grants go on after the books
        b.stop_supervisor()  # and a restart from its own books, which hold that confirmation
        (tmp_path / "status.json").unlink()
        b = bench(tmp_path, "witnessed", auth, b.channel, core)
        wait(lambda: b.node_status().get("synced") == 1)  # the node on: answered at once
        wait(lambda: b.node_status()["committed"] >= 1)
    finally:
        loop.halt()
    final = b.stop_supervisor()["nodes"][str(NODE)]
    used = first + node.actuator.drawn_uj + held(node)
    assert used <= released(final), (used, released(final))
    said = caplog.text
    assert "SYNC sent; no grant to any node until node(s) 1" in said
    assert "node 1 confirmed its books after this start" in said


@pytest.mark.parametrize("core", CORES)
def test_start_without_a_node_grants_at_once_to_others_and_waits_for_its_own_books(
    tmp_path: Path, core: str, caplog: pytest.LogCaptureFixture
) -> None:
    """``--start-without 1``: the start does not wait for node 1 (no other node is kept from
    grants), while node 1's own session still waits for its books: it is granted nothing
    before them, and then nothing is created."""
    b, first, _ = restored_books(tmp_path, "witnessed", None, core, ("--start-without", "1"))
    wait(lambda: b.node_status().get("state") == "SYNCING")
    assert b.status()["core"] == core
    assert b.status()["waiting_for_books"] == [] and b.status()["waiting_why"] is None
    assert b.status()["started_without"] == {"1": released(b.node_status())} != {"1": 0}
    node, loop = b.start_node()
    try:
        wait(lambda: b.node_status()["committed"] >= 3)  # from its books confirmed
    finally:
        loop.halt()
    final = b.stop_supervisor()["nodes"][str(NODE)]
    used = first + node.actuator.drawn_uj + held(node)
    assert used <= released(final), (used, released(final))
    assert "SYNC sent; no grant" not in caplog.text
    assert "started without node(s) 1 (--start-without): not waited for" in caplog.text


@pytest.mark.parametrize("auth", [None, Layout.CLASSIC], ids=KEY_IDS[:2])
@pytest.mark.parametrize("core", CORES)
def test_the_same_restore_under_the_hardened_rules_creates_energy(
    tmp_path: Path, core: str, auth: Layout | None
) -> None:
    """The measurement the witnessed rules answer: the restored books grant again."""
    b, first, _ = restored_books(tmp_path, "hardened", auth, core)
    wait(lambda: b.status().get("core") == core)
    assert b.status()["waiting_for_books"] == []
    node, loop = b.start_node()
    try:

        def created() -> int:
            session = b.node_status()
            if not session:
                return 0
            return first + node.actuator.drawn_uj + held(node) - released(session)

        wait(lambda: created() >= UJ_PER_J)
    finally:
        loop.halt()
    b.stop_supervisor()


@pytest.mark.parametrize("layout", list(Layout))
def test_the_books_answering_a_sync_are_fresh_by_its_nonce(layout: Layout) -> None:
    """The books carry Rc (mJ) where a draw carries its number: judged as a debit number they
    would be stale once Rc's low 16 bits fall below the supervisor's count (after 65.5 J), and
    the start would wait for ever. Their FV is the SYNC's nonce, as the counts'."""
    key = bytes(range(16))

    def side(receives: Direction, seq: int) -> FrameAuth:
        return FrameAuth(
            Codec(), layout, lambda n: key, receives, lambda m: expected_freshness(m, 0, seq)
        )

    node, sup = side(Direction.TO_CLIENT, 10_000), side(Direction.TO_SUPERVISOR, 10_000)
    books = Debit.books(NODE, 0x5A5A, 70_000)  # Rc 70 J: its low 16 bits 4,464, below 10,000
    counts = Debit.counts(NODE, 0x5A5A, 10_000 & 0xFFFF, 40)
    for msg in (books, counts):
        assert [sup.accept(f) for f in node.frames(msg)][-1].message == msg


def _restarted(start_without: tuple[int, ...] = (), core: str = "python") -> SupervisorService:
    """A witnessed supervisor of nodes 1 and 2 on ``core`` restarted from its books (SYNC sent
    to both)."""
    timing = Timing(response_timeout_us=100_000)
    state = SupervisorState(
        10 * UJ_PER_J, 8 * UJ_PER_J, sessions=(Session(1, delivered=UJ_PER_J), Session(2))
    )
    restarted = make_supervisor(
        core,
        [1, 2],
        10 * UJ_PER_J,
        variant="witnessed",
        timing=timing,
        state=state,
        start_without=start_without,
    )
    restarted.power_loss(0, 0x1234)
    service = build_service(restarted, ServiceConfig(), 0)
    for node in (1, 2):
        service.on_message(Telemetry(node, 0, Telemetry.WITNESSED, 0, 0), 1)
    return service


@pytest.mark.parametrize("core", CORES)
def test_a_debt_the_books_bring_refuses_every_grant_and_is_kept_across_a_restart(
    tmp_path: Path, core: str
) -> None:
    """The restored books hold Us 0.2 J; the node's books show 1 J more received since: Us goes
    to -0.8 J (a debt), a grant is refused with the reason, and the state file written in debt
    starts the supervisor again (the loader refused a negative Us before)."""
    timing = Timing(response_timeout_us=100_000)
    state = SupervisorState(UJ_PER_J, UJ_PER_J // 5, sessions=(Session(NODE, delivered=800_000),))
    restored = make_supervisor(
        core, [NODE], UJ_PER_J, variant="witnessed", timing=timing, state=state
    )
    restored.power_loss(0, 0x1234)
    path = tmp_path / "s.json"
    s = build_service(restored, ServiceConfig(state_path=path, fsync=False), 0)
    s.on_message(Telemetry(NODE, 0, Telemetry.WITNESSED, 0, 0), 1)
    s.on_wakeup(1)
    s.on_message(Debit.books(NODE, 0x1234, 1_800), 20)
    s.on_message(Debit.counts(NODE, 0x1234, 0, 0), 21)
    assert s.status()["waiting_for_books"] == [] and s.status()["usable_uj"] == -800_000
    replies: list[dict[str, object]] = []
    s.request_grant(NODE, UJ_PER_J // 10, replies.append)
    assert not [m for m in s.on_wakeup(30) if isinstance(m, Intention)]
    assert "nothing allowed" in str(replies[0]["error"]), replies
    books = load_state(path, "witnessed", (NODE,))
    assert books.usable == -800_000
    again = make_supervisor(core, [NODE], UJ_PER_J, variant="witnessed", timing=timing, state=books)
    assert again.usable == -800_000


@pytest.mark.parametrize("core", CORES)
def test_counts_afresh_ahead_of_the_state_file_are_paid_for_in_the_status_and_on_stderr(
    tmp_path: Path, core: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The state file (C 0, Us 1 J) is older than the node's admission afresh: its counts say
    it holds nothing since (``afresh``) and show debit 3, two the file never held. 2 x 65.535 J
    move from Us to the node's Gs: the status shows the debt and ``ahead_of_image_uj``, stderr
    names the node and the amount, and no grant follows."""
    timing = Timing(response_timeout_us=100_000)
    restored = make_supervisor(core, [NODE], UJ_PER_J, variant="witnessed", timing=timing)
    restored.power_loss(0, 0x1234)
    s = build_service(restored, ServiceConfig(state_path=tmp_path / "s.json", fsync=False), 0)
    s.on_message(Telemetry(NODE, 0, Telemetry.WITNESSED, 0, 0), 1)
    s.on_wakeup(1)
    s.on_message(Debit.books(NODE, 0x1234, None), 20)
    (admit,) = s.on_message(Debit.counts(NODE, 0x1234, 3, 0, afresh=True), 21)
    assert isinstance(admit, Admit) and admit.seq == 4
    debt = UJ_PER_J - 2 * 65_535_000
    assert s.status()["usable_uj"] == debt
    assert s.status()["nodes"][str(NODE)]["ahead_of_image_uj"] == 2 * 65_535_000
    assert "node 1 holds 2 debit numbers this state file never saw" in caplog.text
    assert "131.070000 J moved from the usable budget" in caplog.text
    replies: list[dict[str, object]] = []
    s.request_grant(NODE, UJ_PER_J // 10, replies.append)
    assert not [m for m in s.on_wakeup(30) if isinstance(m, Intention)]


@pytest.mark.parametrize("core", CORES)
def test_sync_is_sent_at_the_start_and_re_sent_until_answered(core: str) -> None:
    s = _restarted(core=core)
    syncs = [m for m in s.on_wakeup(1) if isinstance(m, Admit)]
    assert {(m.node, m.nonce) for m in syncs} == {(1, 0x1234), (2, 0x1234)}
    assert [m for m in s.on_wakeup(100_000) if isinstance(m, Admit)] == []
    again = [m for m in s.on_wakeup(100_001) if isinstance(m, Admit)]
    assert {(m.node, m.nonce) for m in again} == {(1, 0x1234), (2, 0x1234)}


@pytest.mark.parametrize("core", CORES)
def test_no_grant_to_anyone_before_the_nodes_books_and_start_without_skips_one(core: str) -> None:
    s = _restarted(core=core)
    replies: list[dict[str, object]] = []
    s.request_grant(2, UJ_PER_J // 2, replies.append)
    assert [m for m in s.on_wakeup(10) if isinstance(m, Intention)] == [] and replies == []
    assert s.status()["waiting_for_books"] == [1, 2]
    assert "until node(s) 1, 2 answer with their books" in s.status()["waiting_why"]
    out: list[object] = []
    for node, credited_mj in ((1, 1_500), (2, 0)):  # node 1 received 0.5 J after the copy
        assert not [m for m in out if isinstance(m, Intention)]
        out += s.on_message(Debit.books(node, 0x1234, credited_mj), 20)
        out += s.on_wakeup(20)
        out += s.on_message(Debit.counts(node, 0x1234, 0, 0), 21)
    assert s.status()["waiting_for_books"] == [] and s.core.session(1).delivered == 1_500_000
    assert [m.node for m in out if isinstance(m, Intention)] == [2]  # the request waited

    skipping = _restarted((1,), core)  # the operator's override: node 1 not waited for
    assert skipping.status()["waiting_for_books"] == [2]
    skipping.on_message(Debit.books(2, 0x1234, 0), 20)
    skipping.on_message(Debit.counts(2, 0x1234, 0, 0), 21)
    skipping.request_grant(2, UJ_PER_J // 2, replies.append)
    assert [m for m in skipping.on_wakeup(30) if isinstance(m, Intention)]


@pytest.mark.parametrize("core", CORES)
def test_an_earlier_starts_counts_are_counted_and_move_nothing(core: str) -> None:
    """Once the start is over, counts of another nonce whose ltx is not within B of tx (an
    earlier SYNC's, replayed: with a key they verify) are ignored by the rules and counted in
    the node's ``counts_ignored``; the last start's counts again are answered, not counted. The
    ignored counts move no tx, W, C or Gs; the node, which may be left answering a SYNC, is
    re-synced (``resyncs``: a SYNC of its own, nobody else waits), at most once a second."""
    s = _restarted(core=core)
    for node in (1, 2):
        s.on_message(Debit.books(node, 0x1234, 0), 20)
        s.on_message(Debit.counts(node, 0x1234, 0, 0), 21)
    again = s.on_message(Debit.counts(1, 0x1234, 0, 0), 22)
    assert [m for m in again if isinstance(m, Admit)] == [Admit(1, 0x1234 ^ 0x8000, 0, 1)]
    before = s.core.session(1)
    (sync,) = s.on_message(Debit.counts(1, 0x0303, 0, 0x4000), 30)
    after = s.core.session(1)
    assert isinstance(sync, Admit) and sync.nonce == after.sync_nonce and after.resync
    kept = ("tx", "witness", "returns_credited", "delivered", "returned")
    assert all(getattr(after, name) == getattr(before, name) for name in kept)
    shown = s.status()["nodes"]["1"]
    assert (shown["counts_ignored"], shown["resyncs"], s.waiting()) == (1, 1, ())
    s.on_message(Debit.counts(1, sync.nonce, 0, 0), 31)  # its counts before its books: ignored
    s.on_message(Debit.books(1, sync.nonce, 0), 32)
    s.on_message(Debit.counts(1, sync.nonce, 1, 64), 33)
    assert s.core.session(1).phase.name == "IDLE" and s.core.session(1).witness == 64
    assert not s.on_message(Debit.counts(1, 0x0404, 0, 0x4000), 40)  # within a second
    shown = s.status()["nodes"]["1"]
    assert (shown["counts_ignored"], shown["resyncs"]) == (2, 1)


def _story(core: str) -> tuple[list[object], list[dict[str, Any]], list[str]]:
    """A restart on ``core``: SYNC re-sent, a grant asked for while waiting, node 1's books
    (0.5 J more than the restored books) and counts, node 2's, the grant to node 2 carried out.
    Returns the frames sent, the status after each step (but the core's name) and the log."""
    s = _restarted(core=core)
    replies: list[dict[str, object]] = []
    s.request_grant(2, UJ_PER_J // 2, replies.append)
    steps: list[Callable[[], Sequence[object]]] = [
        lambda: s.on_wakeup(10),
        lambda: s.on_wakeup(100_011),
        lambda: s.on_message(Debit.books(1, 0x1234, 1_500), 200_000),
        lambda: s.on_message(Debit.counts(1, 0x1234, 0, 0), 200_001),
        lambda: s.on_message(Debit.books(2, 0x1234, 0), 200_002),
        lambda: s.on_message(Debit.counts(2, 0x1234, 0, 0), 200_003),
        lambda: s.on_wakeup(200_004),
        lambda: s.on_message(Ack(2, s.core.session(2).tx), 200_005),
        lambda: s.on_message(Committed(2, s.core.session(2).tx), 200_006),
    ]
    frames: list[object] = []
    statuses: list[dict[str, Any]] = []
    logger = logging.getLogger("canergy.live.supervisor.service")
    records: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    logger.addHandler(handler)
    try:
        for step in steps:
            frames += step()
            # which core, and so which frame path, is the one difference
            status = s.status()
            statuses.append({k: v for k, v in status.items() if not k.startswith(SAID_APART)})
    finally:
        logger.removeHandler(handler)
    assert replies and replies[0].get("outcome") == "COMMITTED", replies
    return frames, statuses, records


def test_the_c_core_says_and_sends_what_the_python_core_does_through_a_witnessed_start() -> None:
    """The service on either core: the same frames, status and log lines at every step."""
    python, c = _story("python"), _story("c")
    for what, ours, theirs in zip(("frames", "status", "log"), python, c, strict=True):
        assert ours == theirs, what
    assert any("confirmed its books" in line for line in python[2])


def test_start_without_is_refused_outside_the_witnessed_rules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["supervisor", "-i", "virtual", "-c", "x", "--nodes", "1", "--start-without", "1"]
    assert main([*argv, "--state", str(tmp_path / "s.json")]) != 0
    assert "--start-without: only under --variant witnessed" in capsys.readouterr().err
    assert not (tmp_path / "s.json").exists()


@pytest.mark.parametrize(
    ("flags", "why"),
    [
        (("--variant", "hardened", "--start-without", "1"), "only under --variant witnessed"),
        (("--variant", "witnessed", "--start-without", "2"), "node(s) 2 are not nodes it"),
    ],
)
def test_the_gateways_start_without_is_checked_before_its_state_file_is_touched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: tuple[str, ...], why: str
) -> None:
    argv = ["gateway", "--node", "20", "--nodes", "1", "-i", "virtual", "-c", "gw-down"]
    argv += ["--upstream-interface", "virtual", "--upstream-channel", "gw-up", *flags]
    assert main([*argv, "--state", str(tmp_path / "g.json")]) != 0
    assert f"--start-without: {why}" in capsys.readouterr().err
    assert not (tmp_path / "g.json").exists()


@pytest.mark.parametrize("core", CORES)
def test_counts_a_start_ignores_leave_the_witness_alone(
    core: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Review rv2: during a start the core ignores counts under another nonce than its SYNC's
    (an earlier start's, replayed, or forged without a key), as it ignores them after it; the
    service's witness (Python's or C's) then keeps its return-number baseline too, which
    ``hold_resume`` resets (a loss changes nothing)."""
    s = _restarted(core=core)
    reset: list[Debit] = []
    hold_resume = s.witness.hold_resume

    def spy(msg: Debit, credited: int, now: int, hold: bool) -> bool:
        reset.append(msg)
        return hold_resume(msg, credited, now, hold)

    monkeypatch.setattr(s.witness, "hold_resume", spy)
    session = s.core.session(1)
    assert not s.on_message(Debit.counts(1, 0x0303, 0, 0x4000), 10)  # not the SYNC's nonce
    assert s.core.session(1) == session and reset == []
    s.on_message(Debit.books(1, 0x1234, 0), 20)
    s.on_message(Debit.counts(1, 0x1234, 0, 0), 21)  # this start's: the baseline starts again
    assert reset == [Debit.counts(1, 0x1234, 0, 0)]


@pytest.mark.parametrize("core", CORES)
def test_a_copy_taken_while_the_start_waits_for_a_node_that_is_off_creates_nothing(
    tmp_path: Path, core: str
) -> None:
    """protocol.md, 2' (i), on the live stack: the supervisor grants and stops with the node;
    it starts again from its own state file while the node is off and waits for its books;
    the file is copied then (a nightly backup: the session stored IDLE, as it stood); the node
    comes on, its books are confirmed and grants go on; both stop; the copy is put back and the
    supervisor started from it; the node comes on once more. Nothing is created."""
    b = bench(tmp_path, "witnessed", None, core=core)
    node, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("committed", 0) >= 2)
    finally:
        loop.halt()
    b.stop_supervisor()
    used = node.actuator.drawn_uj
    (tmp_path / "status.json").unlink()
    b = bench(tmp_path, "witnessed", None, b.channel, core)  # a reboot, the node off
    wait(lambda: b.status().get("waiting_for_books") == [NODE])
    copy = (tmp_path / "s.json").read_text()
    assert json.loads(copy)["sessions"][str(NODE)]["phase"] == "IDLE"
    node, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("synced") == 1)
        wait(lambda: b.node_status()["committed"] >= 3)  # grants go on after the books
    finally:
        loop.halt()
    b.stop_supervisor()
    used += node.actuator.drawn_uj
    (tmp_path / "s.json").write_text(copy)
    (tmp_path / "status.json").unlink()
    b = bench(tmp_path, "witnessed", None, b.channel, core)  # from the copy
    wait(lambda: b.status().get("waiting_for_books") == [NODE])
    assert b.status()["granted_this_run_uj"] == 0
    node, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("synced") == 1)
        wait(lambda: b.node_status()["committed"] >= 1)
    finally:
        loop.halt()
    final = b.stop_supervisor()["nodes"][str(NODE)]
    used += node.actuator.drawn_uj + held(node)
    assert used <= released(final), (used, released(final))
