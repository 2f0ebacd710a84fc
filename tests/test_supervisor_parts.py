"""Two parts of the supervisor service alone, sans-IO: the JOINs held as evidence
(``canergy.live.supervisor.joins``) and the grant desk (``canergy.live.supervisor.grants``). The
service's own tests (test_witness.py, test_auth_stop.py) run them inside it."""

from __future__ import annotations

from typing import Any

import pytest

from canergy.core import Supervisor
from canergy.live.supervisor.grants import Books, GrantDesk, GrantRequest
from canergy.live.supervisor.intrusions import Intrusions, Refusals
from canergy.live.supervisor.joins import HELD_JOINS, JoinHold
from canergy.live.supervisor.ledger import Ledger
from canergy.live.supervisor.outputs import BooksOut
from canergy.live.supervisor.policy import Limits, TopUp
from canergy.messages import Join, Telemetry

HOLD = 500_000
J = 1_000_000


class Noted:
    """A ``JoinHold`` whose admissions are noted (the nonce admitted and when): what it returns
    to admit, by nonce."""

    def __init__(self, hold: JoinHold) -> None:
        self._hold = hold
        self.admitted: list[tuple[int, int]] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._hold, name)

    def on_telemetry(self, msg: Telemetry, now: int) -> list[int]:
        return self._note(self._hold.on_telemetry(msg, now), now)

    def on_wakeup(self, now: int) -> list[int]:
        return self._note(self._hold.on_wakeup(now), now)

    def _note(self, joins: list[Join], now: int) -> list[int]:
        self.admitted += [(join.nonce, now) for join in joins]
        return [join.nonce for join in joins]


class Desk:
    """A ``JoinHold`` whose admissions are noted (``Noted``)."""

    def __init__(self, authenticated: bool = False, local: frozenset[int] = frozenset()) -> None:
        self.intrusions = Intrusions("supervisor")
        self.refusals = Refusals("supervisor")
        self.hold = Noted(
            JoinHold((3, 4), HOLD, local, self.intrusions, self.refusals, lambda: authenticated)
        )

    @property
    def admitted(self) -> list[tuple[int, int]]:
        return self.hold.admitted


def joining(node: int) -> Telemetry:
    return Telemetry(node, 0, Telemetry.JOINING)


def test_a_join_confirmed_by_the_nodes_report_is_admitted_after_the_hold() -> None:
    d = Desk()
    d.hold.on_join(Join(3, 0x1111))
    assert d.hold.holding(3) and not d.hold.holding(4)
    assert d.hold.on_telemetry(joining(3), 100) == []
    assert d.hold.next_wakeup() == 100 + HOLD
    assert d.hold.on_wakeup(100 + HOLD - 1) == []
    assert d.hold.on_wakeup(100 + HOLD) == [0x1111]
    assert d.admitted == [(0x1111, 100 + HOLD)] and not d.hold.holding(3)
    assert d.hold.next_wakeup() is None and d.intrusions.total == 0


def test_a_report_with_books_refutes_every_join_held() -> None:
    """Each held JOIN is a replay or a forgery: reported, nobody admitted, nothing held."""
    d = Desk()
    for nonce in (1, 2, 3):
        d.hold.on_join(Join(3, nonce))
    d.hold.on_telemetry(joining(3), 0)  # the latest is confirmed...
    assert d.hold.on_telemetry(Telemetry(3, 500), 10) == []  # ...and refuted before its hold
    assert d.hold.on_wakeup(10 * HOLD) == [] and d.admitted == []
    assert d.intrusions.by_node == {3: 3} and not d.hold.holding(3)


def test_with_a_key_a_refuted_join_is_a_refusal_not_a_loud_intrusion() -> None:
    d = Desk(authenticated=True)
    d.hold.on_join(Join(4, 9))
    d.hold.on_telemetry(Telemetry(4, 500), 0)
    assert d.refusals.of_node(4) and d.intrusions.by_node == {4: 1}
    assert d.intrusions.logged_by_node.get(4, 0) == 0  # quiet: anyone can replay one


def test_the_nodes_own_resent_join_is_counted_not_reported() -> None:
    d = Desk()
    d.hold.on_join(Join(3, 7))
    d.hold.on_telemetry(joining(3), 0)
    d.hold.on_wakeup(HOLD)
    d.hold.on_join(Join(3, 7))  # re-sent before the ADMIT reached the node
    d.hold.on_telemetry(Telemetry(3, 0), HOLD + 1)  # its books now
    assert d.hold.nodes[3].resent == 1 and d.intrusions.total == 0


def test_a_local_nodes_join_needs_no_hold() -> None:
    d = Desk(local=frozenset({3}))
    d.hold.on_join(Join(3, 5))
    assert d.hold.on_telemetry(joining(3), 42) == [5]


def test_at_most_the_latest_joins_are_held() -> None:
    d = Desk()
    for nonce in range(HELD_JOINS + 3):
        d.hold.on_join(Join(3, nonce))
    assert [j.nonce for j in d.hold.nodes[3].held] == list(range(3, HELD_JOINS + 3))
    d.hold.on_telemetry(joining(3), 0)
    assert d.hold.on_wakeup(HOLD) == [HELD_JOINS + 2]  # the latest


def test_a_new_join_cancels_an_admission_waiting_for_its_hold() -> None:
    d = Desk()
    d.hold.on_join(Join(3, 1))
    d.hold.on_telemetry(joining(3), 0)
    d.hold.on_join(Join(3, 2))  # another start: only a report after it confirms it
    assert d.hold.on_wakeup(HOLD) == []
    d.hold.on_telemetry(joining(3), HOLD)
    assert d.hold.on_wakeup(2 * HOLD) == [2]


class Replies:
    def __init__(self) -> None:
        self.got: list[dict[str, Any]] = []

    def __call__(self, reply: dict[str, Any]) -> None:
        self.got.append(reply)


def test_the_desk_grants_a_request_within_every_cap() -> None:
    desk = GrantDesk(Limits(max_grant=2 * J), None)
    replies = Replies()
    assert desk.one_shot(GrantRequest(3, J, replies), 3, None, Books(5 * J, 0), 0) == J
    assert replies.got == []


def test_the_desk_refuses_what_a_cap_would_cut_and_says_which() -> None:
    desk = GrantDesk(Limits(max_grant=2 * J), None)
    replies = Replies()
    assert desk.one_shot(GrantRequest(3, 3 * J, replies), 3, None, Books(5 * J, 0), 0) is None
    (reply,) = replies.got
    assert reply["error"].startswith("refused by limits or budget (2.000000 J allowed: --max-grant")
    assert desk.one_shot(GrantRequest(3, J, replies), 3, None, Books(J // 2, 0), 0) is None
    assert "0.500000 J allowed" in replies.got[1]["error"], replies.got


def test_the_desk_refuses_a_level_its_record_cannot_hold() -> None:
    desk = GrantDesk(Limits(), None)
    replies = Replies()
    level = 2**31  # µJ: near what a node's record holds
    assert desk.one_shot(GrantRequest(3, 2**31, replies), 3, level, Books(2**40, 0), 0) is None
    assert "the most its record holds" in replies.got[0]["error"]


def test_the_rate_limiter_counts_what_began() -> None:
    """A second of tokens at 1 J/s: a grant taken empties them, half a second refills half."""
    desk = GrantDesk(Limits(max_grant=J, rate_uj_per_s=J), TopUp(J))
    books = Books(100 * J, 0)
    assert desk.top_up(0, books, 0) == J
    desk.took(J)
    assert desk.top_up(0, books, 0) == 0
    assert desk.top_up(0, books, 500_000) == J // 2


def _ledger(saved: list[int], *, listen_only: bool = False) -> Ledger:
    core = Supervisor((1,), 10**6)
    out = BooksOut(core, None, save=lambda: saved.append(core.state.injected))
    return Ledger(core, out, listen_only=listen_only)


def test_the_ledger_writes_an_injection_before_anything_else() -> None:
    saved: list[int] = []
    ledger = _ledger(saved)
    ledger.open(5)
    assert saved == [5] and ledger.injected_this_run == 5 and ledger.saves == 1


def test_the_ledger_writes_once_a_step_and_only_when_the_record_changed() -> None:
    saved: list[int] = []
    ledger = _ledger(saved)
    ledger.open(0)
    ledger.save_if_dirty()
    assert saved == [0]  # nothing changed: nothing written
    ledger.dirty = True  # the step's Persist actions (the service sets it for each)
    ledger.save_if_dirty()
    ledger.save_if_dirty()
    assert saved == [0, 0] and not ledger.dirty


def test_a_listen_only_ledger_writes_nothing_and_takes_no_injection() -> None:
    saved: list[int] = []
    ledger = _ledger(saved, listen_only=True)
    ledger.open(0)
    assert saved == []
    with pytest.raises(ValueError, match="listen-only"):
        ledger.open(5)
