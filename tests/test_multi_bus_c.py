"""A supervisor over two buses on the compiled core (``--core c --bus ... --bus ...``: one C
supervisor per bus, ``canergy.ccore.buses``) side by side with the same supervisor on the
Python core: the same frames to both, through the builder and the bus loop, give the same
frames on each bus, the same books, the same state file and the same status but for which core
and frame path ran. The C core's frame path takes frames on both buses, and a frame on one bus
in the name of a node of the other settles nothing."""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest

from canergy.bus_keys import session_key
from canergy.ccore.supervisor import missing
from canergy.codec import Codec
from canergy.core.state import Phase
from canergy.live.supervisor.build import CoreConfig, SupervisorConfig, build_supervisor
from canergy.live.supervisor.service import ServiceConfig
from canergy.live.supervisor.witness import RETURN_HOLD_MIN_US
from canergy.messages import Ack, Committed, Message, Return, Telemetry

J = 1_000_000
NAMES = ("left", "right")
NODES = {"left": (1, 2), "right": (1, 3)}
"""Node 1 on both buses, node 2 on the left only, node 3 on the right only."""
KEYS = tuple(session_key(i, n) for i, name in enumerate(NAMES) for n in NODES[name])
CODEC = Codec()
CHANGES = ("core", "frame_path", "frame_path_frames")
"""What the status says differently on the two cores."""


class _Run:
    """A supervisor on ``kind``'s core over two virtual buses, the nodes' ends of them, a
    clock that moves only when told."""

    def __init__(self, tmp: Path, kind: str, hold: bool) -> None:
        self.now = 1_000_000
        self.state = tmp / f"{kind}-{hold}.json"
        channels = [f"mbc-{name}-{uuid.uuid4().hex}" for name in NAMES]
        self.sup_buses = [can.Bus(interface="virtual", channel=ch) for ch in channels]
        self.node_buses = [can.Bus(interface="virtual", channel=ch) for ch in channels]
        config = SupervisorConfig(
            core=CoreConfig(KEYS, 3 * J, kind=kind, state_path=self.state),
            service=ServiceConfig(
                state_path=self.state,
                fsync=False,
                bus_names=NAMES,
                return_hold_us=RETURN_HOLD_MIN_US if hold else None,
            ),
        )
        self.built = build_supervisor(config, self.sup_buses, clock=lambda: self.now)
        self.service = self.built.service
        self.heard: dict[str, list[tuple[int, bytes]]] = {name: [] for name in NAMES}

    def close(self) -> None:
        self.built.close()
        for bus in (*self.sup_buses, *self.node_buses):
            bus.shutdown()

    def _poll(self, until: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            self.built.loop.poll(0.01)
            for name, bus in zip(NAMES, self.node_buses, strict=True):
                while (frame := bus.recv(0)) is not None:
                    self.heard[name].append((frame.arbitration_id, bytes(frame.data)))
            if until():
                return
        raise AssertionError("the supervisor never got there")

    def received(self) -> int:
        return int(self.service.status()["frames_received"])

    def send(self, bus: str, msg: Message) -> None:
        """``msg`` from a node on ``bus``; returns once the supervisor's loop took it."""
        self.now += 1_000
        before = self.received()
        ident, data = CODEC.encode(msg)
        frame = can.Message(arbitration_id=ident, data=data, is_extended_id=True)
        self.node_buses[NAMES.index(bus)].send(frame)
        self._poll(lambda: self.received() > before)

    def grant(self, bus: str, node: int, amount: int, frames: int) -> None:
        """A one-shot grant; returns once ``frames`` frames in all were heard on the buses."""
        self.service.request_grant(session_key(NAMES.index(bus), node), amount, lambda r: None)
        self._poll(lambda: sum(map(len, self.heard.values())) >= frames)

    def frames_in_c(self) -> int:
        return int(self.service.status()["frame_path_frames"])

    def phase(self, bus: str, node: int) -> Phase:
        return self.service.core.session(session_key(NAMES.index(bus), node)).phase


def _scenario(
    tmp: Path, kind: str, hold: bool = False
) -> tuple[dict[str, Any], Any, dict[str, Any], _Run]:
    """Every node reports; grants on both buses, answered; a stray ACK on the wrong bus; a
    return on one bus (``hold``: held by the witness until the node's TELEMETRY confirms it),
    then a grant on the other that needs it. The status, books, state file, and the run (its
    frames heard)."""
    run = _Run(tmp, kind, hold)
    c = kind == "c"
    counts: list[int] = []
    try:
        for bus in NAMES:
            for node in NODES[bus]:
                run.send(bus, Telemetry(node, 0))
        run.grant("left", 1, 2 * J, 1)
        run.grant("right", 1, J, 2)
        counts.append(run.frames_in_c())
        run.send("left", Ack(1, 1))
        counts.append(run.frames_in_c())
        run.send("right", Ack(1, 1))
        counts.append(run.frames_in_c())
        run.send("left", Committed(1, 1))
        run.send("right", Committed(1, 1))
        run.send("left", Return(1, 1, 1_000))  # 1 J back, into the left bus's Us
        run.send("left", Telemetry(1, 1_000, 0, 1))  # it confirms return 1 (the witness)
        run.now += RETURN_HOLD_MIN_US if hold else 0  # the hold has passed: it is credited
        run.grant("right", 3, J // 2, 6)  # all of Us was granted: this needs the return
        run.send("left", Ack(3, 1))  # node 3 is the right bus's: nothing on the left takes it
        assert run.phase("right", 3) is Phase.WAIT_ACK
        assert run.phase("left", 1) is Phase.IDLE and run.phase("right", 1) is Phase.IDLE
        run.send("right", Ack(3, 1))
        run.send("right", Committed(3, 1))
        counts.append(run.frames_in_c())
        tables = (run.service.heard, run.service.witness, run.service.joins)
        status = run.service.status()
        books = run.service.core.state
        saved = json.loads(run.state.read_text())
    finally:
        run.close()
    if c:  # each bus's answers went through C, one more frame each; the tables are C's
        assert counts[0] == 4 and counts[1:3] == [5, 6] and counts[3] > 6, counts
        assert [table.implementation for table in tables] == ["c"] * 3
    return status, books, saved, run


@pytest.mark.parametrize("hold", [False, True])
def test_two_buses_on_the_c_core_match_the_python_core(tmp_path: Path, hold: bool) -> None:
    if missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")
    py_status, py_books, py_saved, py_run = _scenario(tmp_path, "python", hold)
    c_status, c_books, c_saved, c_run = _scenario(tmp_path, "c", hold)
    assert c_run.heard == py_run.heard  # every frame on each bus, byte for byte, in order
    assert [len(c_run.heard[name]) for name in NAMES] == [3, 4]  # INTENTION, COMMIT, ACK
    assert c_books == py_books
    assert c_books.usable == J // 2 and c_status["conservation"]["holds"]
    assert c_saved == py_saved and list(c_saved["sessions"]) == [
        "left/1",
        "left/2",
        "right/1",
        "right/3",
    ]
    assert (py_status["core"], py_status["frame_path"]) == ("python", "python")
    assert (c_status["core"], c_status["frame_path"]) == ("c", "c")
    assert "frame_path_off" not in c_status
    # C took the answers whole and decoded the rest, Python's path the answers
    assert c_status["frame_path_frames"] >= 12
    assert 4 <= py_status["frame_path_frames"] < c_status["frame_path_frames"]
    for key in CHANGES:
        del py_status[key], c_status[key]
    assert c_status == py_status
    assert c_status["nodes"]["right/1"]["committed_uj"] == J


def test_the_c_cores_record_of_two_buses_restarts_either_core(tmp_path: Path) -> None:
    """The state file the C core wrote over two buses (Us summed) is what the Python core
    starts from, and the C core again: the same books."""
    from canergy.live.supervisor.build import open_core

    _, books, _, run = _scenario(tmp_path, "c")
    for kind in ("python", "c"):
        config = SupervisorConfig(
            core=CoreConfig(KEYS, 3 * J, kind=kind, state_path=run.state, keep_books=False),
            service=ServiceConfig(bus_names=NAMES),
        )
        core = open_core(config, 0)
        assert core.implementation == kind and core.state.usable == books.usable
        assert [s.delivered for s in core.state.sessions] == [s.delivered for s in books.sessions]


@pytest.mark.parametrize("fd", [True, False], ids=["fd", "classic"])
def test_with_a_key_over_several_buses_the_status_says_the_c_frame_path_runs(fd: bool) -> None:
    """--auth over several buses: the C core runs and so does its frame path (a fallback to
    frames checked and signed in Python would say ``python`` and why; that each bus's answers
    are taken in C: tests/test_multi_bus_c_auth.py)."""
    if missing() is not None:
        pytest.fail(f"the compiled core is not built: {missing()}")
    from canergy.auth.keys import new_master
    from canergy.live.supervisor.build import AuthConfig

    masters = (new_master(1), new_master(1))
    buses = [can.Bus(interface="virtual", channel=f"mbk-{uuid.uuid4().hex}") for _ in NAMES]
    try:
        config = SupervisorConfig(
            core=CoreConfig(KEYS, J, kind="c"),
            service=ServiceConfig(bus_names=NAMES),
            auth=AuthConfig(masters[0], fd=fd, bus_keys=masters),  # node 1 on both: two keys
        )
        built = build_supervisor(config, buses)
        status = built.service.status()
        built.close()
    finally:
        for bus in buses:
            bus.shutdown()
    assert (status["core"], status["frame_path"]) == ("c", "c")
    assert "frame_path_off" not in status
