"""The live supervisor re-syncs a node whose window is used up (witnessed rules): a grant
refused as beyond the window sends that node a SYNC with a fresh nonce, counted in its status
(``resyncs``); once the node has answered, the next grant goes through. Both cores, no bus: the
service's frames are handed to a witnessed node core and its answers back."""

from __future__ import annotations

from typing import Any

import pytest

from canergy.ccore.supervisor import CompiledSupervisor
from canergy.core import Client, Supervisor, Timing
from canergy.core.state import ClientState, Outcome, Phase, Session, SupervisorState
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import RESYNC_GAP_US, ServiceConfig, SupervisorService
from canergy.messages import Admit, Direction, Message, Telemetry

TIMING = Timing(response_timeout_us=1000, command_timeout_us=5000, return_retry_us=5000)


def _pump(service: SupervisorService, node: Client, out: Any, now: int) -> None:
    """Deliver the service's frames to the node and the node's answers back, until quiet."""
    queue: list[Message] = list(out)
    while queue:
        msg = queue.pop(0)
        if msg.TYPE.direction is Direction.TO_CLIENT:
            queue += [a.message for a in node.receive(msg, now) if hasattr(a, "message")]
        else:
            queue += list(service.on_message(msg, now))


def _booked(core: Any, tx: int) -> tuple[Any, SupervisorService, Client]:
    """Node 1 booked at ``tx`` (W 10, C 3, Gs 5 mJ) under a witnessed supervisor of ``core``
    and its service; the node has said it runs these rules."""
    session = Session(1, tx=tx, witness=10, returns_credited=3, delivered=5000)
    state = SupervisorState(10**7, 10**7, sessions=(session,))
    sup = core([1], 10**7, variant="witnessed", timing=TIMING, state=state)
    service = build_service(sup, ServiceConfig(fsync=False), 0)
    booked = ClientState(1, credited=5000, last_tx=tx, outcome=Outcome.COMMITTED, return_seq=3)
    node = Client(1, variant="witnessed", timing=TIMING, state=booked)
    _pump(service, node, [Telemetry(1, 5, Telemetry.WITNESSED)], 0)
    return sup, service, node


@pytest.mark.parametrize("core", [Supervisor, CompiledSupervisor], ids=["python", "c"])
def test_a_node_refused_as_beyond_its_window_is_resynced_and_granted(core: Any) -> None:
    """tx 200, W 10 (an admission lifted tx and moved no W): the grant's begin is refused as
    beyond the window and the node re-synced (status ``resyncs`` 1, a SYNC sent) while the
    grant waits; the node answers, its counts move W to its ltx, and the same grant is then
    committed (one reply, no error)."""
    sup, service, node = _booked(core, tx=200)
    replies: list[dict[str, Any]] = []
    service.request_grant(1, 1_000_000, replies.append)
    out = list(service.on_wakeup(1))
    assert [m for m in out if isinstance(m, Admit)], "a SYNC to the node"
    assert replies == []  # the grant waits for the re-sync, as for a node not heard yet
    assert service.status()["nodes"]["1"]["resyncs"] == 1
    _pump(service, node, out, 1)  # the re-sync ends, and the same grant is begun at once
    assert node.state.phase is Phase.IDLE and sup.session(1).phase is Phase.IDLE
    assert sup.session(1).witness == sup.session(1).tx == 200 + TIMING.window + 1
    assert node.state.usable == 1_000_000 and sup.session(1).delivered == 5000 + 1_000_000
    assert [(r.get("error"), r.get("outcome")) for r in replies] == [(None, "COMMITTED")]
    assert service.status()["nodes"]["1"]["resyncs"] == 1


@pytest.mark.parametrize("core", [Supervisor, CompiledSupervisor], ids=["python", "c"])
def test_a_node_whose_counts_are_ignored_is_resynced(core: Any) -> None:
    """Review rv2 live: a booked node's answers to two stale ADMITs are lost, so its counts for
    a third are 3B past tx and ignored; the service re-syncs it at once (``counts_ignored`` 1,
    ``resyncs`` 1), the node is confirmed and the next grant is committed."""
    sup, service, node = _booked(core, tx=10)
    node.receive(Admit(1, 1, 0, 0), 0)  # its answer lost
    node.receive(Admit(1, 2, 0, 0), 0)  # its answer lost
    _pump(service, node, [Admit(1, 3, 0, 0)], 0)
    shown = service.status()["nodes"]["1"]
    assert (shown["counts_ignored"], shown["resyncs"]) == (1, 1)
    assert node.state.phase is Phase.IDLE and sup.session(1).tx == 10 + 4 * TIMING.window
    replies: list[dict[str, Any]] = []
    service.request_grant(1, 1_000_000, replies.append)
    _pump(service, node, service.on_wakeup(1), 1)
    assert node.state.usable == 1_000_000
    assert all("error" not in r for r in replies)


@pytest.mark.parametrize("core", [Supervisor, CompiledSupervisor], ids=["python", "c"])
def test_ignored_counts_resync_a_node_at_most_once_a_second(core: Any) -> None:
    """A counts frame the rules ignore (an earlier start's, replayed: it verifies for its key
    epoch) re-syncs the node, but a replay within ``RESYNC_GAP_US`` of the last re-sync only
    counts: a replayer costs the node at most one re-sync a second."""
    _, service, node = _booked(core, tx=10)
    node.receive(Admit(1, 1, 0, 0), 0)  # its answer lost
    node.receive(Admit(1, 2, 0, 0), 0)  # its answer lost
    stale = [a.message for a in node.receive(Admit(1, 3, 0, 0), 0) if hasattr(a, "message")]
    _pump(service, node, stale, 0)  # ignored: the node re-synced and confirmed
    shown = service.status()["nodes"]["1"]
    assert (shown["counts_ignored"], shown["resyncs"]) == (1, 1)
    _pump(service, node, stale, RESYNC_GAP_US - 1)  # replayed within the gap
    shown = service.status()["nodes"]["1"]
    assert (shown["counts_ignored"], shown["resyncs"]) == (2, 1)
    _pump(service, node, stale, RESYNC_GAP_US)  # and once the gap is over
    shown = service.status()["nodes"]["1"]
    assert (shown["counts_ignored"], shown["resyncs"]) == (3, 2)
