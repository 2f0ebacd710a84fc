"""The checker's re-sync move (``Bounds.resyncs``, ``canergy check --resyncs``): the witnessed
supervisor re-syncs one idle node (``witnessed.resync_session``) with a fresh SYNC nonce.

A window closed by a written-off transaction is opened only by a re-sync, the move is taken in
the searches, and within small bounds with older copies of either record no re-sync creates
energy (both engines store the same states: ``test_check_engine``)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from canergy.check import Bounds, check, replay
from canergy.check.explore import step_from_json, step_json
from canergy.check.model import RESYNC_NONCE, Model, Step, StepKind, World, initial_world
from canergy.cli import main
from canergy.core.state import Phase
from canergy.core.variants import VARIANTS
from canergy.messages import Committed, Debit

K = StepKind
CLOSING = Bounds(
    transactions=2,
    losses=1,
    duplicates=0,
    power_losses=0,
    retries=0,
    in_flight=2,
    units=2,
    resyncs=1,
)
"""One node, two units; a COMMITTED may be lost and the supervisor then writes it off."""


def _take(model: Model, w: World, kind: StepKind) -> tuple[Step, World]:
    """The first step of ``kind`` that applies."""
    for step in model.steps(w):
        if step.kind is kind:
            nxt = model.apply(w, step)
            if nxt is not None:
                return step, nxt
    raise AssertionError(f"no {kind.value} step applies")


def _is_books(m: object) -> bool:
    return isinstance(m, Debit) and m.is_books


def _closed(model: Model) -> World:
    """Transaction 1 committed by the node, its COMMITTED lost, written off by the supervisor:
    tx 1, W 0 (the node showed only its ACK), so transaction 2 is beyond the window."""
    w = initial_world(model.bounds)
    for kind in (K.BEGIN, K.DELIVER, K.DELIVER, K.DECIDE, K.DELIVER):
        w = _take(model, w, kind)[1]
    assert [type(m) for m, _ in w.flight] == [Committed]
    for kind in (K.LOSE, K.SUPERVISOR_TIMER):
        w = _take(model, w, kind)[1]
    s = w.sup.sessions[0]
    assert (s.phase, s.tx, s.witness) == (Phase.IDLE, 1, 0) and not w.flight
    return w


def test_a_window_closed_by_a_write_off_is_opened_by_a_resync() -> None:
    model = Model(VARIANTS["witnessed"], CLOSING)
    w = _closed(model)
    begins = [st for st in model.steps(w) if st.kind is K.BEGIN]
    assert begins and all(model.apply(w, st) is None for st in begins)  # WindowClosed
    step, w = _take(model, w, K.RESYNC)
    assert step.nonce == RESYNC_NONCE + 1 and w.resynced == 1
    assert w.sup.sessions[0].resync and w.sup.sessions[0].phase is Phase.SYNCING
    assert not [st for st in model.steps(w) if st.kind is K.RESYNC]  # one re-sync allowed
    while w.flight:  # the SYNC, the books then the counts, the confirmation
        frames = sorted((m for m, _ in w.flight), key=lambda m: not _is_books(m))
        nxt = model.apply(w, Step(K.DELIVER, message=frames[0]))
        assert nxt is not None
        w = nxt
    s, c = w.sup.sessions[0], w.clients[0]
    assert (s.phase, s.tx, s.witness, c.phase, c.last_tx) == (Phase.IDLE, 2, 2, Phase.IDLE, 2)
    w = _take(model, w, K.BEGIN)[1]
    assert (w.sup.sessions[0].phase, w.sup.sessions[0].tx) == (Phase.WAIT_ACK, 3)
    assert w.ledger().dissipated >= 0


def test_without_resyncs_the_closed_window_stays_closed() -> None:
    """The same bound with no re-sync: nothing begins again, nothing is offered to re-sync."""
    model = Model(VARIANTS["witnessed"], replace(CLOSING, resyncs=0))
    w = _closed(model)
    assert all(st.kind is not K.RESYNC for st in model.steps(w))
    assert all(model.apply(w, st) is None for st in model.steps(w) if st.kind is K.BEGIN)


def test_other_rules_offer_no_resync() -> None:
    for name in ("hardened", "paper"):
        model = Model(VARIANTS[name], CLOSING)
        assert all(st.kind is not K.RESYNC for st in model.steps(initial_world(CLOSING)))


SMALL = [
    # the node's record put back to its copy before its last write, a frame lost
    Bounds(transactions=1, old_copies=1, duplicates=0, power_losses=0, in_flight=2, resyncs=1),
    # the supervisor's state file put back to its copy before its last write, two nodes
    Bounds(
        clients=2,
        supervisor_old_copies=1,
        transactions=1,
        losses=0,
        duplicates=0,
        power_losses=0,
        in_flight=2,
        timeouts=2,
        resyncs=1,
    ),
    # a node losing its books (JOIN), two transactions
    Bounds(
        transactions=2,
        nv_losses=1,
        losses=0,
        duplicates=0,
        power_losses=0,
        in_flight=2,
        timeouts=3,
        resyncs=1,
    ),
]


@pytest.mark.parametrize("bounds", SMALL, ids=["old copy", "supervisor old copy", "join"])
def test_resyncs_create_no_energy(bounds: Bounds) -> None:
    result = check("witnessed", bounds, workers=1)
    assert result.complete and result.violations == 0
    without = check("witnessed", replace(bounds, resyncs=0), workers=1)
    assert result.states > without.states  # the re-syncs were explored


def test_a_resync_in_a_trace_replays_from_json() -> None:
    """A re-sync's nonce goes into a JSON trace and back, and the trace replays."""
    model = Model(VARIANTS["witnessed"], CLOSING)
    w = _closed(model)
    step, _ = _take(model, w, K.RESYNC)
    data = json.loads(json.dumps(step_json(step)))
    assert data == {"kind": "resync", "node": 1, "nonce": RESYNC_NONCE + 1}
    assert step_from_json(data) == step
    assert replay(model, [step_from_json(data)])[0].resynced == 1
    assert step.describe() == f"resync node 1 (nonce {RESYNC_NONCE + 1:#x})"


def test_cli_resyncs(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["check", "--variant", "witnessed", "--transactions", "1", "--losses", "0"]
    argv += ["--duplicates", "0", "--power-losses", "0", "--workers", "1"]
    assert main([*argv, "--resyncs", "1", "--json"]) == 0
    with_resyncs = json.loads(capsys.readouterr().out)
    assert main([*argv, "--json"]) == 0
    without = json.loads(capsys.readouterr().out)
    assert with_resyncs["bounds"]["resyncs"] == 1 and without["bounds"]["resyncs"] == 0
    assert with_resyncs["states"] > without["states"]
    assert main([*argv, "--resyncs", "1"]) == 0
    assert "re-syncs 1" in capsys.readouterr().out
    assert main(["check", "--resyncs", "1"]) == 2
    assert "no re-sync" in capsys.readouterr().err
    assert main(["check", "--topology", "chain", "--variant", "witnessed", "--resyncs", "1"]) == 2
    assert "--resyncs" in capsys.readouterr().err


def test_the_ledger_counts_us_while_a_node_is_only_resynced() -> None:
    """While a start waits for books, Us is left out of the ledger (it may be an older
    copy's); a re-sync restores nothing and grants to others go on, so Us counts: energy
    created during a re-sync shows at once, not only when it ends."""
    from canergy.core.state import Phase, Session, SupervisorState
    from canergy.ledger import supervisor_usable

    def us(resync: bool) -> int:
        s = Session(1, phase=Phase.SYNCING, tx=3, witness=3, sync_nonce=7, resync=resync)
        return supervisor_usable(SupervisorState(9000, 9000, sessions=(s,)))

    assert (us(resync=True), us(resync=False)) == (9000, 0)
