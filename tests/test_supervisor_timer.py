"""The supervisor's timer: the earliest deadline of its sessions, kept without a scan per frame."""

from __future__ import annotations

from canergy.core import Acknowledged, Action, Client, Send, Supervisor, Timing
from canergy.messages import ToClient, ToSupervisor

NODES = range(1, 5)
TIMING = Timing(response_timeout_us=100, retries=2)


def earliest(sup: Supervisor) -> int | None:
    deadlines = [s.deadline for s in sup.state.sessions if s.deadline is not None]
    return min(deadlines) if deadlines else None


def exchange(sup: Supervisor, clients: dict[int, Client], actions: list[Action], now: int) -> None:
    """Carry every frame to its receiver until the exchange is quiet, commits included."""
    queue = list(actions)
    while queue:
        action = queue.pop(0)
        if isinstance(action, Acknowledged):
            queue += sup.commit(action.node, now)
        elif isinstance(action, Send) and isinstance(action.message, ToClient):
            queue += clients[action.message.node].receive(action.message, now)
        elif isinstance(action, Send) and isinstance(action.message, ToSupervisor):
            queue += sup.receive(action.message, now)


def test_many_transactions_between_reads_keep_the_timer_right_and_its_heap_small() -> None:
    sup = Supervisor(NODES, 10**9, timing=TIMING)
    clients = {n: Client(n, timing=TIMING) for n in NODES}
    assert sup.get_timer() is None
    now = 0
    for i in range(200):  # deadlines set and cleared, never read in between
        now += 7
        exchange(sup, clients, sup.begin(1 + i % 4, 1000, now), now)
    assert [s.delivered for s in sup.state.sessions] == [50_000] * 4  # every one committed
    # 400 deadlines set and cleared unread: the heap was dropped for a rebuild, not grown
    assert len(sup._deadlines) <= 2 * len(NODES) + 16 + 1
    open_now = [sup.begin(n, 1000, now + n) for n in (2, 3)]  # left waiting for their ACKs
    assert all(open_now)
    assert sup.get_timer() == earliest(sup) == now + 2 + TIMING.response_timeout_us


def test_a_state_set_from_outside_is_read_afresh() -> None:
    sup = Supervisor(NODES, 10**9, timing=TIMING)
    sup.begin(1, 1000, 0)
    assert sup.get_timer() == TIMING.response_timeout_us
    later = Supervisor(NODES, 10**9, timing=TIMING)
    later.begin(4, 1000, 50)
    sup.state = later.state  # as a gateway or a restore sets it
    assert sup.get_timer() == 50 + TIMING.response_timeout_us
