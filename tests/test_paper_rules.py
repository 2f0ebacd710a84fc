"""Transitions of the paper-literal rules (Figs. 3 and 4) that the hazards rely on."""

from __future__ import annotations

from dataclasses import replace

from canergy.core import Acknowledged, Resolved, RolledBack, Send, Timing
from canergy.core.paper import PaperClient as C
from canergy.core.paper import PaperSupervisor as S
from canergy.core.state import ClientState, Decision, Outcome, Phase, Session
from canergy.messages import Ack, Commit, Committed, FinalAck, Intention, Return, StatusRequest

T = Timing(response_timeout_us=100, retries=1, command_timeout_us=100)
OPEN = Session(node=1, phase=Phase.WAIT_ACK, tx=4, reserved=2000, tries=1, deadline=100)


def test_timeout_defines_a_new_intention_for_the_same_reservation() -> None:
    s, actions, _ = S.timer(T, OPEN, 100)
    assert (s.tx, s.reserved, s.phase) == (5, 2000, Phase.WAIT_ACK)
    assert actions == (Send(Intention(1, 5, 2, 0)),)


def test_wrong_ack_defines_a_new_intention() -> None:
    s, actions, _ = S.receive(T, OPEN, Ack(1, 3), 10)
    assert s.tx == 5 and actions == (Send(Intention(1, 5, 2, 0)),)
    s, actions, _ = S.receive(T, OPEN, Ack(1, 4), 10)
    assert s.phase is Phase.ACKED and actions == (Acknowledged(1, 4),)


def test_status_requests_then_passivity_timeout() -> None:
    waiting = replace(OPEN, phase=Phase.WAIT_CONFIRM, decision=Decision.COMMIT)
    asked, actions, _ = S.timer(T, waiting, 100)
    assert asked.phase is Phase.WAIT_STATUS and actions == (Send(StatusRequest(1, 4)),)
    done, actions, credit = S.timer(T, asked, 300)
    assert (done.phase, done.reserved, done.delivered, credit) == (Phase.IDLE, 0, 2000, 0)
    assert actions == (Resolved(1, 4, Outcome.WRITTEN_OFF, 2000), Send(FinalAck(1, 4)))


def test_every_return_is_credited() -> None:
    s, _, credit = S.receive(T, Session(1), Return(1, 1, 3), 0)
    s, _, again = S.receive(T, s, Return(1, 1, 3), 0)
    assert credit == again == 3000 and s.returned == 6000


def test_supervisor_reset_loses_the_transaction_budget() -> None:
    s = S.power_loss(replace(OPEN, delivered=500), 0)
    assert (s.phase, s.tx, s.reserved, s.delivered) == (Phase.IDLE, 0, 0, 2500)


def test_client_rolls_back_a_timeout_commit_on_a_new_intention() -> None:
    held, _ = C.receive(T, ClientState(1), Intention(1, 4, 2, 0), 0)
    committed, actions = C.command_timer(T, held, 100)
    assert committed.timeout_commit and committed.usable == 2000
    assert actions[-1] == Send(Committed(1, 4))
    spent = replace(committed, usable=500, spent=1500)
    fresh, actions = C.receive(T, spent, Intention(1, 5, 2, 0), 150)
    assert actions == (RolledBack(1, 4, 500), Send(Ack(1, 5)))
    assert (fresh.usable, fresh.credited, fresh.held_tx) == (0, 1500, 5)


def test_client_forgets_after_timeout_n_and_after_reset() -> None:
    held, _ = C.receive(T, ClientState(1), Intention(1, 4, 2, 0), 0)
    done, _ = C.receive(T, held, Commit(1, 4, 2), 10)
    assert done.phase is Phase.AWAIT_SUPERVISOR
    forgot, _ = C.command_timer(T, done, 10 + T.quiet_timeout_us)
    assert forgot.phase is Phase.IDLE and forgot.held_tx == 0
    again, actions = C.receive(T, forgot, Intention(1, 4, 2, 0), 500)
    assert again.phase is Phase.AWAIT_COMMAND and actions == (Send(Ack(1, 4)),)
    assert C.power_loss(done, 0).phase is Phase.IDLE
