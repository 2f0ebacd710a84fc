"""Cross-checks without a key: the supervisor judges what a node sends against its books.

What no honest node sends (a level or a fresh RETURN above what its books let it hold, an answer
to a transaction never begun) is reported as an intrusion; a RETURN or answer of that kind moves
nothing. An honest node, whose telemetry may lag a return credited meanwhile, raises nothing.
"""

from __future__ import annotations

from collections.abc import Sequence

import pytest

from canergy.core import Client, Send, Supervisor, Timing
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.messages import Ack, Committed, Message, Return, Telemetry, ToClient
from canergy.units import UJ_PER_J

TIMING = Timing(response_timeout_us=10_000, retries=3)


def pump(service: SupervisorService, client: Client, out: Sequence[Message], now: int) -> None:
    """Deliver frames both ways until nothing is left."""
    queue = list(out)
    while queue:
        msg = queue.pop(0)
        if isinstance(msg, ToClient):
            queue += [a.message for a in client.receive(msg, now) if isinstance(a, Send)]
        else:
            queue += service.on_message(msg, now)


def granted(amount: int) -> tuple[SupervisorService, Client]:
    """A node that was granted ``amount`` µJ and reported its level."""
    service = build_service(
        Supervisor((1,), 10 * UJ_PER_J, timing=TIMING),
        ServiceConfig(fsync=False, status_period_us=10**12),
        0,
    )
    client = Client(1, timing=TIMING)
    service.on_message(Telemetry(1, 0), 0)
    answers: list[dict[str, object]] = []
    service.request_grant(1, amount, answers.append)
    pump(service, client, service.on_wakeup(1), 1)
    assert answers[0]["outcome"] == "COMMITTED" and client.state.usable == amount
    return service, client


def test_a_level_above_the_books_is_reported() -> None:
    service, _ = granted(2 * UJ_PER_J)
    service.on_message(Telemetry(1, 2000), 10)  # the truth
    assert service.intrusions.total == 0
    service.on_message(Telemetry(1, 2001), 20)  # 1 mJ more than it can hold
    assert service.intrusions.by_node == {1: 1}
    assert "its books allow 2.000000 J" in service.intrusions.recent[-1]["kind"]


def test_a_level_lagging_a_credited_return_is_not() -> None:
    service, client = granted(2 * UJ_PER_J)
    stale = Telemetry(1, 2000)  # sent before the return below, arriving after it
    pump(
        service,
        client,
        [a.message for a in client.give_back(UJ_PER_J, 30) if isinstance(a, Send)],
        30,
    )
    assert service.core.session(1).returned == UJ_PER_J
    service.on_message(stale, 40)
    assert service.intrusions.total == 0
    service.on_message(stale, 40 + service.config.lost_after_us + 1)  # long after: impossible
    assert service.intrusions.total == 1


def test_a_return_above_what_a_node_can_hold_moves_nothing() -> None:
    service, _ = granted(2 * UJ_PER_J)
    usable = service.core.state.usable
    assert service.on_message(Return(1, 1, 2001), 50) == ()
    assert service.core.state.usable == usable and service.core.session(1).returned == 0
    assert service.intrusions.by_node == {1: 1}
    service.on_message(Return(1, 1, 2000), 60)  # all it holds: fine
    assert service.core.session(1).returned == 2 * UJ_PER_J and service.intrusions.total == 1


def test_an_answer_to_a_transaction_never_begun_moves_nothing() -> None:
    service, _ = granted(UJ_PER_J)
    tx = service.core.session(1).tx
    delivered = service.core.session(1).delivered
    for forged in (Ack(1, tx + 1), Committed(1, tx + 5)):
        assert service.on_message(forged, 70) == ()
    assert service.intrusions.total == 2 and service.core.session(1).delivered == delivered
    service.on_message(Committed(1, tx), 80)  # a late duplicate of the genuine answer: fine
    assert service.intrusions.total == 2


pytestmark = pytest.mark.usefixtures("both_cores")
"""Each test on the Python core and on the compiled one (tests/conftest.py)."""
