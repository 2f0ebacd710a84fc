"""The supervisor saves its books once per loop pass, and never sends a frame the file on disk
does not already cover (issue 18: persist once per loop pass)."""

from __future__ import annotations

import json
from collections import deque
from pathlib import Path
from typing import Any

import can
import pytest

from canergy.codec import Codec
from canergy.core import Supervisor
from canergy.core.state import SupervisorState
from canergy.live.bus_group import BusGroup
from canergy.live.runtime import BusRuntime
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.multi_bus import BusPort, BusRouter
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.state_file import BooksWriter, state_json
from canergy.messages import Ack, Commit, Committed, Direction, Intention, Message, Telemetry

NODES = tuple(range(1, 17))
CODEC = Codec()


class _CheckedBus(can.BusABC):
    """Frames queued by the test come out of ``recv``; every ``send`` first compares the state
    file with the books in memory: a frame may only leave once the file covers it."""

    def __init__(self, service: SupervisorService, state: Path) -> None:
        super().__init__(channel="checked")
        self.service, self.books = service, state
        self.inbox: deque[can.Message] = deque()
        self.sent: list[Message] = []

    def queue(self, *messages: Message) -> None:
        for msg in messages:
            arbitration_id, data = CODEC.encode(msg)
            self.inbox.append(can.Message(arbitration_id=arbitration_id, data=data))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        on_disk = json.loads(self.books.read_text())
        del on_disk["checksum"]
        assert on_disk == state_json(self.service.core.state, "hardened"), "sent before saved"
        decoded = CODEC.decode(msg.arbitration_id, msg.data, direction=Direction.TO_CLIENT)
        assert decoded is not None
        self.sent.append(decoded)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.popleft() if self.inbox else None), False


def _service(tmp_path: Path, nodes: tuple[int, ...] = NODES) -> SupervisorService:
    config = ServiceConfig(state_path=tmp_path / "books.json", fsync=False)
    return build_service(Supervisor(nodes, 10**12), config, 0)


def _count_saves(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    saves: list[int] = []
    real = BooksWriter.save

    def counted(self: BooksWriter, state: SupervisorState) -> None:
        saves.append(1)
        real(self, state)

    monkeypatch.setattr(BooksWriter, "save", counted)
    return saves


def _grant_to_all(service: SupervisorService, replies: list[dict[str, Any]]) -> None:
    for node in service.nodes:
        service.request_grant(node, 1_000_000, replies.append)


def _phase_by_phase(
    bus: _CheckedBus, poll: Any, saves: list[int], nodes: tuple[int, ...]
) -> list[int]:
    """Drive every node through one transaction, each answer of all nodes queued at once: the
    saves after each pass."""
    per_pass, tx = [], {}
    bus.queue(*(Telemetry(n, 0) for n in nodes))
    for answer in (None, Ack, Committed):
        if answer is not None:
            bus.queue(*(answer(n, tx[n]) for n in nodes))
        before = len(saves)
        poll()
        per_pass.append(len(saves) - before)
        tx |= {m.node: m.tx for m in bus.sent if isinstance(m, Intention)}
    return per_pass


class _NoPasses:
    """The service's Handler methods only, no begin_pass/end_pass (a wrapping handler)."""

    def __init__(self, service: SupervisorService) -> None:
        self.service = service

    def __getattr__(self, name: str) -> Any:
        if name in ("begin_pass", "end_pass"):
            raise AttributeError(name)
        return getattr(self.service, name)


@pytest.mark.usefixtures("both_cores")  # one bus: on the Python core and the compiled one
@pytest.mark.parametrize(("passes", "saves"), [(True, [1, 1, 1]), (False, [16, 16, 16])])
def test_a_drained_batch_is_saved_once_and_sent_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, passes: bool, saves: list[int]
) -> None:
    """16 TELEMETRY, then 16 ACKs, then 16 COMMITTEDs, each lot drained by one poll: one save
    per pass; a handler that takes no passes keeps the per-step order (a save per step, each
    before its frames)."""
    counted = _count_saves(monkeypatch)
    service = _service(tmp_path)
    bus = _CheckedBus(service, tmp_path / "books.json")
    handler = service if passes else _NoPasses(service)
    # time stands still: on a loaded machine a real clock let the intentions' retry deadline
    # pass between two polls, and the re-sends added saves and frames the test did not drive
    runtime = BusRuntime(
        bus, handler, codec=CODEC, receives=Direction.TO_SUPERVISOR, clock=lambda: 0
    )
    replies: list[dict[str, Any]] = []
    _grant_to_all(service, replies)
    per_pass = _phase_by_phase(bus, lambda: runtime.poll(0), counted, NODES)
    bus.shutdown()
    assert per_pass == saves
    kinds = [type(m).__name__ for m in bus.sent]
    assert kinds == ["Intention"] * 16 + ["Commit"] * 16
    assert [r["outcome"] for r in replies] == ["COMMITTED"] * 16
    assert service.core.is_quiescent()


def test_several_buses_share_one_pass(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Over two buses the service holds every bus's frames until the last runtime ends the pass,
    then saves once, and each frame goes out on its own bus."""
    saves = _count_saves(monkeypatch)
    keys = (*range(1, 9), *(1 << 8 | n for n in range(1, 9)))
    service = _service(tmp_path, keys)
    buses = [_CheckedBus(service, tmp_path / "books.json") for _ in range(2)]
    router = BusRouter()
    for i, bus in enumerate(buses):
        port = BusPort(service, i, router, deadlines=i == 0)
        router.runtimes.append(BusRuntime(bus, port, codec=CODEC, receives=Direction.TO_SUPERVISOR))
    for key in keys:
        service.request_grant(key, 1_000_000, lambda r: None)
    for runtime in router.runtimes:
        runtime.begin_pass()
    for runtime in router.runtimes:
        for n in range(1, 9):
            runtime.receive(_frame(Telemetry(n, 0)))
    before = len(saves)
    router.runtimes[0].end_pass()
    assert len(saves) == before and not buses[0].sent and not buses[1].sent  # still held
    router.runtimes[1].end_pass()  # the outermost end: saved once, then sent
    assert len(saves) == before + 1
    for bus in buses:
        assert [(type(m), m.node) for m in bus.sent] == [(Intention, n) for n in range(1, 9)]
    # the same through BusGroup's loop (reader threads): every frame still after its save
    for bus in buses:
        bus.queue(*(Ack(m.node, m.tx) for m in bus.sent))
    group = BusGroup(router.runtimes)
    try:
        for _ in range(200):
            group.poll(0.05)
            if all(len(bus.sent) == 16 for bus in buses):
                break
    finally:
        group.close()
        for bus in buses:
            bus.shutdown()
    for bus in buses:
        assert [(type(m), m.node) for m in bus.sent[8:]] == [(Commit, n) for n in range(1, 9)]


def _frame(msg: Message) -> can.Message:
    arbitration_id, data = CODEC.encode(msg)
    return can.Message(arbitration_id=arbitration_id, data=data)
