"""A supervisor started from a state file older than a node's admission afresh (issue 40, once a
residual of docs/protocol.md): the node drew from grants the image still counts in Us, lost its
books and was admitted afresh; its books cannot say what it received, but its counts show how
many debits the supervisor held since the image. The most those draws can take moves from Us
to Gs (``witnessed.ahead_of_image``), in both supervisor cores, and nothing moves when the books
are known or the counts show no draw since the image."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import pytest

from canergy.ccore.supervisor import CompiledSupervisor
from canergy.check import Bounds, check
from canergy.core import AheadOfImage, Client, Send, Supervisor, Timing
from canergy.messages import AMOUNT_MAX_MJ, QUANTUM_UJ, Debit, Direction

CORES = pytest.mark.parametrize("core", [Supervisor, CompiledSupervisor], ids=["python", "c"])
TIMING = Timing(response_timeout_us=10, command_timeout_us=10, return_retry_us=10)
DRAW_MAX = AMOUNT_MAX_MJ * QUANTUM_UJ
INITIAL = 10_000_000


def exchange(actions: list[Any], sup: Any, node: Client, now: int) -> list[Any]:
    """Deliver every frame sent until nobody sends; every action of ``sup`` is returned."""
    queue, said = list(actions), list(actions)
    while queue:
        a = queue.pop(0)
        if isinstance(a, Send):
            if a.message.TYPE.direction is Direction.TO_CLIENT:
                queue += node.receive(a.message, now)  # type: ignore[arg-type]
            else:
                answer = sup.receive(a.message, now)
                said += answer
                queue += answer
    return said


def granted_drawn_then(core: Any, draws: int, lose_books: bool) -> tuple[Any, Client, Any]:
    """A node granted 1 J after the supervisor's first state file, drawing ``draws`` times
    250 mJ, then losing its books (JOIN, admitted afresh) or not; the supervisor put back to
    that first file and started, its SYNC answered. Returns the restored supervisor, the node
    and every action of the start."""
    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = Client(1, variant="witnessed", timing=TIMING)
    image = sup.state
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    for _ in range(draws):
        exchange(node.spend(250_000, 0), sup, node, 0)
    if lose_books:
        exchange(node.books_lost(0x0303, 0), sup, node, 0)
        assert node.state.credited_unknown and sup.session(1).returns_credited == draws + 1
    restored = core([1], 0, variant="witnessed", timing=TIMING, state=image)
    restored.power_loss(1, nonce=0x55)
    said = exchange(restored.handle_timer(1), restored, node, 1)
    assert restored.unconfirmed() == ()
    return restored, node, said


@CORES
@pytest.mark.parametrize("draws", [1, 3])
def test_an_image_older_than_an_admission_afresh_pays_for_every_draw_since(
    core: Any, draws: int
) -> None:
    """Before, Us was 10 J again after the start while the node had used ``draws`` x 250 mJ of
    the image's budget (the checker's NV bound: 16 steps)."""
    restored, node, said = granted_drawn_then(core, draws, lose_books=True)
    ahead = [a for a in said if isinstance(a, AheadOfImage)]
    assert ahead == [AheadOfImage(1, draws)] and ahead[0].amount == draws * DRAW_MAX
    assert restored.session(1).delivered == draws * DRAW_MAX
    assert restored.state.usable == INITIAL - draws * DRAW_MAX  # a debt: no grant until covered
    assert restored.state.usable + node.state.spent <= INITIAL
    with pytest.raises(Exception, match="usable"):
        restored.begin(1, 1000, 2)


@CORES
def test_a_node_admitted_afresh_without_a_draw_since_the_image_costs_nothing(core: Any) -> None:
    """Counts at C + 1: no debit held since the image but the admission, so nothing the image
    counts in Us was used; Gs and Us stay, and the start grants again."""
    restored, node, said = granted_drawn_then(core, 0, lose_books=True)
    assert not [a for a in said if isinstance(a, AheadOfImage)]
    assert restored.session(1).delivered == 0 and restored.state.usable == INITIAL
    assert node.state.spent == 0


@CORES
def test_known_books_ahead_of_the_image_move_gs_to_them_and_no_further(core: Any) -> None:
    """An ordinary restore: the node kept its books (Rc 1 J) and drew twice since the image;
    its books move Gs up to 1 J, and nothing more leaves Us."""
    restored, node, said = granted_drawn_then(core, 2, lose_books=False)
    assert not [a for a in said if isinstance(a, AheadOfImage)]
    assert restored.session(1).delivered == 1_000_000
    assert restored.state.usable == INITIAL - 1_000_000
    assert node.state.usable + node.state.spent == 1_000_000


def python_node(state: Any) -> Client:
    node = Client(1, variant="witnessed", timing=TIMING)
    node.state = state
    return node


def c_node(state: Any) -> Any:
    from test_c_witnessed import _CClientNode

    return _CClientNode(state)


NODES = pytest.mark.parametrize("make_node", [python_node, c_node], ids=["python-node", "c-node"])


@CORES
@NODES
def test_a_node_put_back_and_found_behind_then_an_older_supervisor_image_creates_nothing(
    core: Any, make_node: Any
) -> None:
    """Restores one after the other, each start confirmed before the next (once the exception
    of protocol.md's residual): the node, granted 1 J, is copied (a backup), granted 1 J more
    and draws 1.5 J; its record is put back to the copy (Rc 1 J, q 0) and its RESUME is found
    behind (C 4): admitted afresh, the copy's Rc kept as its floor. The supervisor's state file
    is then put back to a copy from before both grants (Us 10 J, C 0). Its start takes the
    floor (Gs 1 J) and the counts afresh at q 4: three debits the image never held, so 3 x
    65.535 J leave Us. Before, Us was 9 J while the node had used 1.5 J of it: 0.5 J created."""
    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = make_node(Client(1, variant="witnessed", timing=TIMING).state)
    image = sup.state
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    copy = node.state
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    for _ in range(3):
        exchange(node.spend(500_000, 0), sup, node, 0)
    spent = node.state.spent
    assert spent == 1_500_000 and sup.session(1).returns_credited == 3
    node = make_node(copy)  # the node's record put back to its copy
    exchange(node.power_loss(1, nonce=0x0404), sup, node, 1)
    assert node.state.credited_unknown and node.state.credited == 1_000_000  # the floor
    assert node.state.return_seq == sup.session(1).returns_credited == 4  # confirmed
    restored = core([1], 0, variant="witnessed", timing=TIMING, state=image)
    restored.power_loss(2, nonce=0x55)
    said = exchange(restored.handle_timer(2), restored, node, 2)
    assert restored.unconfirmed() == ()
    (ahead,) = [a for a in said if isinstance(a, AheadOfImage)]
    assert ahead == AheadOfImage(1, 3) and ahead.amount == 3 * DRAW_MAX
    assert restored.session(1).delivered == 1_000_000 + 3 * DRAW_MAX
    assert restored.state.usable + spent + node.state.usable <= INITIAL


def test_only_a_supervisor_image_older_than_an_admission_afresh_pays() -> None:
    """The checker, one node that may lose power and its books: without a state file put back
    no start ever pays for debits (every quiescent state loses at most the bound's 1 mJ: the
    counts of a start are never more than C + 1, whatever the node's own faults); with the
    file's backups put back the rule fires (a loss of 65.535 J or more) and nothing is
    created."""
    bounds = Bounds(
        clients=1,
        transactions=1,
        losses=0,
        duplicates=0,
        power_losses=1,
        nv_losses=1,
        retries=0,
        timeouts=3,
        in_flight=2,
    )
    alone = check("witnessed", bounds)
    assert alone.complete and alone.violations == 0
    assert alone.worst_quiescent_dissipation < DRAW_MAX
    backups = check("witnessed", replace(bounds, supervisor_old_copies=1, supervisor_backups=True))
    assert backups.complete and backups.violations == 0, backups.counterexample
    assert backups.worst_quiescent_dissipation >= DRAW_MAX


def forged_counts_afresh(
    core: Any, make_node: Any, numbers: int, when: str = "between"
) -> tuple[Any, Any, list[Any]]:
    """A node granted 1 J that drew 250 mJ; the supervisor's start (no image put back), the
    node's books taken, then counts afresh forged at q = C + 1 + ``numbers`` before the node's
    genuine counts; both sides run until quiet. ``when``: the forged counts ``"between"`` the
    node's books and counts, ``"books-forged"`` (after books of no Rc forged too, both before
    the node's answer), ``"first"`` (before any books) or ``"after"`` (once the start has
    ended). The supervisor, the node, every action."""
    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = make_node(Client(1, variant="witnessed", timing=TIMING).state)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    exchange(node.spend(250_000, 0), sup, node, 0)
    sup.power_loss(1, nonce=0x55)
    (sync,) = [a.message for a in sup.handle_timer(1) if isinstance(a, Send)]
    answers = [a.message for a in node.receive(sync, 1) if isinstance(a, Send)]
    (books,) = [m for m in answers if m.is_books]
    (counts,) = [m for m in answers if m.is_counts]
    c = sup.session(1).returns_credited
    forged = Debit.counts(1, counts.nonce, (c + 1 + numbers) & 0xFFFF, counts.amount_mj, True)
    arrive = {
        "between": [books, forged, counts],
        "books-forged": [Debit.books(1, counts.nonce, None), forged, books, counts],
        "first": [forged, books, counts],
        "after": [books, counts, forged],
    }[when]
    said: list[Any] = []
    for msg in arrive:
        said += exchange(sup.receive(msg, 1), sup, node, 1)
    for t in range(2, 2_000, 10):  # the C node re-sends its counts at 300 µs (SCENE)
        said += exchange([*node.handle_timer(t), *sup.handle_timer(t)], sup, node, t)
    return sup, node, said


def paid_by_the_next_grant(sup: Any, node: Any, debt: int) -> int:
    """The debt injected, 1 J granted: what the node received beyond the 1 J (nothing created:
    checked here)."""
    before = node.state.usable
    if debt:
        sup.inject(debt)
    exchange(sup.begin(1, 1_000_000, 2_000), sup, node, 2_000)
    exchange(sup.commit(1, 2_000), sup, node, 2_000)
    held = node.state.usable + node.state.spent
    assert sup.state.usable + held <= INITIAL + debt
    return int(node.state.usable - before - 1_000_000)


@CORES
@NODES
@pytest.mark.parametrize("numbers", [128, 32_766], ids=["found-behind", "most-debt"])
def test_forged_counts_afresh_without_a_key_cost_a_debt_and_create_nothing(
    core: Any, make_node: Any, numbers: int
) -> None:
    """docs/security.md's residual without a key: a forger that read the SYNC's nonce on the
    bus sends counts afresh (flags 0x16) after the node's books and before its genuine counts.
    ``numbers`` x 65.535 J leave Us for Gs: a debt (at most 32,766 numbers, 2.15 MJ), no grant
    to any node until an injection covers it. The supervisor's answer moves C past the node's
    count: unless C comes round to the node's q + 1 on the 16-bit wire (the largest forgery),
    the node is found behind and writes off what it held (0.75 J), admitted afresh. Either way
    its next INTENTION pays it nothing of the Gs the forgery raised (a fresh intention sets
    Rc = Gs; known books 2.15 MJ behind read as behind on the 24-bit wire)."""
    sup, node, said = forged_counts_afresh(core, make_node, numbers)
    assert [a for a in said if isinstance(a, AheadOfImage)] == [AheadOfImage(1, numbers)]
    debt = numbers * DRAW_MAX
    assert sup.state.usable == INITIAL - 1_000_000 - debt
    assert sup.session(1).delivered == 1_000_000 + debt
    with pytest.raises(Exception, match="usable"):
        sup.begin(1, 1000, 2_000)
    if numbers < 32_766:  # found behind: written off, admitted afresh
        assert node.state.usable == 0 and node.state.credited_unknown
    else:  # C came round to q + 1: confirmed
        assert node.state.usable == 750_000 and node.state.credited == 1_000_000
    assert paid_by_the_next_grant(sup, node, debt) == 0


@CORES
@pytest.mark.parametrize("when", ["between", "books-forged"])
def test_no_forged_counts_afresh_pays_a_node_anything(core: Any, when: str) -> None:
    """Every 61st q the forgery can take (and the ends), against the Python node, after the
    node's genuine books or with books of no Rc forged before them: each books its debt, none
    pays the node anything, none creates energy."""
    for numbers in (*range(1, 32_767, 61), 32_765, 32_766):
        sup, node, _ = forged_counts_afresh(core, python_node, numbers, when)
        assert sup.session(1).delivered == 1_000_000 + numbers * DRAW_MAX, numbers
        assert paid_by_the_next_grant(sup, node, numbers * DRAW_MAX) == 0, numbers


@CORES
@NODES
@pytest.mark.parametrize("when", ["first", "after"])
@pytest.mark.parametrize("numbers", [1, 128, 32_766])
def test_forged_counts_afresh_before_any_books_or_after_the_start_move_nothing(
    core: Any, make_node: Any, when: str, numbers: int
) -> None:
    """Counts afresh forged where the start awaits no counts, before the node's books reach
    the supervisor (``first``) or once its counts have ended the start (``after``), are dropped:
    no debt, no write-off, the node confirmed with its 0.75 J, and the next grant is an
    ordinary one (a rule that took them as counts would book a debt or refuse the grant)."""
    sup, node, said = forged_counts_afresh(core, make_node, numbers, when=when)
    assert [a for a in said if isinstance(a, AheadOfImage)] == []
    assert sup.state.usable == INITIAL - 1_000_000
    assert sup.session(1).delivered == 1_000_000
    assert node.state.usable == 750_000 and node.state.credited == 1_000_000
    assert sup.unconfirmed() == ()
    assert paid_by_the_next_grant(sup, node, 0) == 0
    assert node.state.usable == 1_750_000


def granted_drawn_and_put_back(core: Any, sup: Any, node: Any, copy: Any, now: int) -> None:
    """1 J more granted and 1.5 J drawn, then the supervisor's books put back to ``copy()`` and
    started: its start takes the node's books (Gs raised to its Rc) and nothing is created."""
    exchange(sup.begin(1, 1_000_000, now), sup, node, now)
    exchange(sup.commit(1, now), sup, node, now)
    for _ in range(3):
        exchange(node.spend(500_000, now), sup, node, now)
    rc = node.state.credited
    assert node.state.spent == 1_500_000 and node.state.usable == rc - 1_500_000
    assert rc == sup.session(1).delivered  # the node holds all it was given
    restored = core([1], 0, variant="witnessed", timing=TIMING, state=copy())
    assert restored.session(1).delivered < rc  # the copy is behind the node
    restored.power_loss(now + 1, nonce=0x66)
    exchange(restored.handle_timer(now + 1), restored, node, now + 1)
    assert restored.unconfirmed() == ()
    assert restored.session(1).delivered >= rc  # the copy's Gs raised to the node's Rc
    held = node.state.usable + node.state.spent
    assert restored.state.usable + held <= INITIAL


@CORES
@NODES
def test_a_state_file_copied_before_a_reboot_and_put_back_after_it_creates_nothing(
    core: Any, make_node: Any
) -> None:
    """protocol.md (2' (i)): a copy written before a start of the supervisor's from its own
    record stays inside the theorem. Tried on the cores: 1 J granted, the state file copied
    (a nightly backup), the supervisor reboots and its start is confirmed, 1 J more granted
    and 1.5 J drawn, then the copy put back and started. Its start takes the node's books
    (Rc 2 J) and counts: what the node holds and used is within what the image's Us gave."""
    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = make_node(Client(1, variant="witnessed", timing=TIMING).state)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    copy = sup.state
    sup.power_loss(1, nonce=0x55)  # the reboot: a start from its own record
    exchange(sup.handle_timer(1), sup, node, 1)
    assert sup.unconfirmed() == ()
    granted_drawn_and_put_back(core, sup, node, lambda: copy, 2)


@CORES
@NODES
def test_a_state_file_copied_while_a_start_waits_for_a_silent_node_creates_nothing(
    core: Any, make_node: Any, tmp_path: Any
) -> None:
    """protocol.md (2' (i)): a copy written while a start of the supervisor's from its own
    record waits for the node's books is inside the theorem (the file holds the session as it
    stood at the start, after the start's write-off). Tried on the cores through the state
    file: 1 J granted and 1 J more in flight (acknowledged, not committed), the supervisor
    reboots while the node is off (its SYNC unanswered: the start writes the 1 J in flight off,
    so the file differs from any copy written before the reboot), the file copied then (a
    nightly backup), the node comes back and the start is confirmed, 1 J more granted (the node
    takes the 1 J written off with it: Rc 3 J) and 1.5 J drawn; the copy put back and started:
    Us 7 J beside the node's 3 J, nothing created."""
    from canergy.live.supervisor.state_file import load_state, save_state

    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = make_node(Client(1, variant="witnessed", timing=TIMING).state)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    save_state(tmp_path / "before.json", sup.state, "witnessed", fsync=False)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)  # acknowledged; no commit before the reboot
    sup.power_loss(1, nonce=0x55)  # the reboot: a start from its own record
    unanswered = [a for a in sup.handle_timer(1) if isinstance(a, Send)]
    assert unanswered and sup.unconfirmed() == (1,)  # the SYNC is lost: the node is off
    save_state(tmp_path / "copy.json", sup.state, "witnessed", fsync=False)
    exchange(sup.handle_timer(1_000), sup, node, 1_000)  # the SYNC again, answered
    assert sup.unconfirmed() == ()

    def copy() -> Any:
        books = load_state(tmp_path / "copy.json", "witnessed", (1,))
        older = load_state(tmp_path / "before.json", "witnessed", (1,))
        assert (books.usable, books.sessions[0].delivered) == (INITIAL - 2_000_000, 2_000_000)
        assert (older.usable, older.sessions[0].delivered) == (INITIAL - 1_000_000, 1_000_000)
        return books

    granted_drawn_and_put_back(core, sup, node, copy, 1_001)
    assert node.state.credited == 3_000_000 and node.state.usable == 1_500_000


@CORES
@NODES
def test_a_node_copied_while_its_start_waits_for_the_supervisor_creates_nothing(
    core: Any, make_node: Any
) -> None:
    """protocol.md (2' (i)): a copy of the node's record written while its own start after a
    power loss waits (RESUMING, the supervisor not answering) is inside the theorem. Tried on
    the cores: 1 J granted, the node loses power while the supervisor is down (its RESUME
    lost), its record is copied then, the RESUME answered once the supervisor is back, 1 J more
    granted and 1.5 J drawn; the record put back to the copy and started: found behind, the
    node holds nothing it was not given and the supervisor's books pay for what it used."""
    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = make_node(Client(1, variant="witnessed", timing=TIMING).state)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    lost = [a for a in node.power_loss(1, nonce=0x0404) if isinstance(a, Send)]
    assert lost and node.state.usable == 1_000_000  # the RESUME, lost: the supervisor is off
    copy = node.state
    exchange(node.handle_timer(1_000), sup, node, 1_000)  # the RESUME again, answered
    assert node.state.usable == 1_000_000 and sup.unconfirmed() == ()
    exchange(sup.begin(1, 1_000_000, 1_001), sup, node, 1_001)
    exchange(sup.commit(1, 1_001), sup, node, 1_001)
    for _ in range(3):
        exchange(node.spend(500_000, 1_001), sup, node, 1_001)
    spent = node.state.spent
    assert spent == 1_500_000 and sup.state.usable == INITIAL - 2_000_000
    node = make_node(copy)  # the node's record put back to the copy
    exchange(node.power_loss(1_002, nonce=0x0505), sup, node, 1_002)
    exchange(node.handle_timer(2_000), sup, node, 2_000)
    assert node.state.phase.name == "IDLE" and sup.unconfirmed() == ()
    assert sup.state.usable + spent + node.state.usable <= INITIAL
    assert node.state.usable == 0  # found behind: the copy's budget dropped
    assert sup.state.usable == INITIAL - 2_000_000  # 0.5 J lost, nothing created


@CORES
@NODES
def test_a_node_copied_while_it_answers_a_sync_creates_nothing(core: Any, make_node: Any) -> None:
    """protocol.md (2' (i)): a copy of the node's record written while it answers a SYNC
    (SYNCING: the supervisor rebooted from its own record, the confirmation not yet come) is
    inside the theorem. Tried on the cores: 1 J granted and 1 J more acknowledged, not
    committed, when the supervisor reboots; the node answers its SYNC (dropping the intention
    it held and settling its window ahead: a record unlike any before the SYNC) and those
    answers are lost; the record is copied then; the SYNC again is answered and confirmed,
    1 J more granted (with the 1 J written off: Rc 3 J) and 1.5 J drawn; the record put back
    to the copy and started: found behind, the node holds nothing, Us 7 J, 1.5 J lost."""
    sup = core([1], INITIAL, variant="witnessed", timing=TIMING)
    node = make_node(Client(1, variant="witnessed", timing=TIMING).state)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)
    exchange(sup.commit(1, 0), sup, node, 0)
    exchange(sup.begin(1, 1_000_000, 0), sup, node, 0)  # acknowledged; no commit before the reboot
    held = node.state
    sup.power_loss(1, nonce=0x55)  # the reboot: a start from its own record
    syncs = [a.message for a in sup.handle_timer(1) if isinstance(a, Send)]
    answers = [a for m in syncs for a in node.receive(m, 1) if isinstance(a, Send)]
    assert answers and node.state.phase.name == "SYNCING"  # its books and counts, lost
    copy = node.state
    assert (held.held_tx, copy.held_tx) == (2, 0) and copy.last_tx > held.last_tx
    exchange(sup.handle_timer(1_000), sup, node, 1_000)  # the SYNC again, answered
    assert node.state.phase.name == "IDLE" and sup.unconfirmed() == ()
    exchange(sup.begin(1, 1_000_000, 1_001), sup, node, 1_001)
    exchange(sup.commit(1, 1_001), sup, node, 1_001)
    for _ in range(3):
        exchange(node.spend(500_000, 1_001), sup, node, 1_001)
    spent = node.state.spent
    assert spent == 1_500_000 and node.state.credited == 3_000_000
    assert sup.state.usable == INITIAL - 3_000_000
    node = make_node(copy)  # the node's record put back to the copy
    exchange(node.power_loss(1_002, nonce=0x0505), sup, node, 1_002)
    exchange(node.handle_timer(2_000), sup, node, 2_000)
    assert node.state.phase.name == "IDLE" and sup.unconfirmed() == ()
    assert node.state.usable == 0  # found behind: the copy's budget dropped
    assert sup.state.usable == INITIAL - 3_000_000  # 1.5 J lost, nothing created
