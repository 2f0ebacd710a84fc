"""``--auth`` over several buses on the compiled core's frame path (``canergy supervisor --core c
--auth KEY --bus ... --bus ...``: one C supervisor per bus, each holding its bus's node keys)
side by side with the Python core on the usual path (Python verifies, the rules run, Python
signs), in both layouts (FD: the MAC inside the frame; classic: a MAC frame after each message,
paired by each bus's ``FrameAuth``): the same frames on each bus, byte for byte, the same books,
state file and status (refusals by reason, intrusions) but for which core and frame path ran,
and the same freshness notes on each bus. The compiled run takes each bus's genuine answers in
C: it does not fall back."""

from __future__ import annotations

import copy
import json
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from support.ccore_built import release

from canergy.auth.frames import FrameAuth, Layout
from canergy.auth.keys import Key
from canergy.bus_keys import session_key
from canergy.ccore.supervisor import make_supervisor
from canergy.codec import Codec
from canergy.core.supervisor import SupervisorCore
from canergy.core.timing import Timing
from canergy.live.supervisor.build import (
    AuthConfig,
    CoreConfig,
    RunningSupervisor,
    SupervisorConfig,
    build_supervisor,
)
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import (
    Abort,
    Aborted,
    Ack,
    Commit,
    Committed,
    Direction,
    Intention,
    Message,
    Telemetry,
)

J = 1_000_000
NAMES = ("left", "right")
NODES = {"left": (1, 2), "right": (1, 3)}
"""Node 1 on both buses (two sessions, each under its bus's key), 2 on the left only, 3 on the
right only."""
KEYS = tuple(session_key(i, n) for i, name in enumerate(NAMES) for n in NODES[name])
MASTERS = (Key("master", 1, bytes(range(16))), Key("master", 1, bytes(range(16, 32))))
"""Each bus's master key (``AuthConfig.bus_keys``): node 1 has a key on each bus, and a frame of
one session does not verify as the other's (the builder refuses one key for both)."""
T = Timing(response_timeout_us=1_000, retries=2)
CODEC = Codec()
CHANGES = ("core", "frame_path", "frame_path_frames", "frame_path_off")
"""What the status says differently on the two paths (with a key the Python core's bus loop
verifies and decodes each frame, and its status says so: ``frame_path_off``)."""


def signed(msg: Message, fv: int, fd: bool, bus: int, *, flip: bool = False) -> list[can.Message]:
    """``msg`` from its node on bus index ``bus`` with freshness value ``fv`` under its key
    (``MASTERS[bus]``'s): one FD frame, or the classic frame and its MAC frame; ``flip``: one
    bit of the MAC flipped."""
    layout = Layout.FD if fd else Layout.CLASSIC
    key = MASTERS[bus].node_key
    frames = FrameAuth(CODEC, layout, key, Direction.TO_CLIENT, lambda m: fv).frames(msg)
    if flip:
        frames[-1].data[-1] ^= 0x01
    return frames


def frame_key(frame: can.Message) -> tuple[int, bytes, bool, bool]:
    return frame.arbitration_id, bytes(frame.data), frame.is_fd, frame.bitrate_switch


# -- scripted, through the builder and the bus loop on two python-can virtual buses -------------


class _Run:
    """A supervisor on ``kind``'s core with a key over two virtual buses (``build_supervisor``,
    its ``BusGroup``), the nodes' ends of them, a clock that moves only when told."""

    def __init__(self, tmp: Path, kind: str, fd: bool) -> None:
        self.now = 1_000_000
        self.fd = fd
        self.state = tmp / f"{kind}-{fd}.json"
        channels = [f"mbca-{name}-{uuid.uuid4().hex}" for name in NAMES]
        self.sup_buses = [can.Bus(interface="virtual", channel=ch) for ch in channels]
        self.node_buses = [can.Bus(interface="virtual", channel=ch) for ch in channels]
        config = SupervisorConfig(
            core=CoreConfig(KEYS, 3 * J, kind=kind, timing=T, state_path=self.state),
            service=ServiceConfig(state_path=self.state, fsync=False, bus_names=NAMES),
            auth=AuthConfig(MASTERS[0], fd=fd, bus_keys=MASTERS),
        )
        self.built = build_supervisor(config, self.sup_buses, clock=lambda: self.now)
        self.service = self.built.service
        self.heard: dict[str, list[tuple[int, bytes, bool, bool]]] = {name: [] for name in NAMES}

    def close(self) -> None:
        self.built.close()
        for bus in (*self.sup_buses, *self.node_buses):
            bus.shutdown()

    def poll(self, until: Callable[[], bool]) -> None:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            self.built.loop.poll(0.01)
            for name, bus in zip(NAMES, self.node_buses, strict=True):
                while (frame := bus.recv(0)) is not None:
                    self.heard[name].append(frame_key(frame))
            if until():
                return
        raise AssertionError("the supervisor never got there")

    def received(self) -> int:
        return int(self.service.status()["frames_received"])

    def send(self, bus: str, frames: list[can.Message]) -> None:
        """``frames`` from a node on ``bus``; returns once the supervisor's loop took them."""
        self.now += 100
        before = self.received()
        for frame in frames:
            self.node_buses[NAMES.index(bus)].send(copy.copy(frame))
        self.poll(lambda: self.received() >= before + len(frames))

    def answer(self, bus: str, msg: Message, fv: int, *, flip: bool = False) -> None:
        self.send(bus, signed(msg, fv, self.fd, NAMES.index(bus), flip=flip))

    def grant(self, bus: str, node: int, amount: int) -> None:
        """A one-shot grant; returns once its INTENTION was heard on ``bus``."""
        before = len(self.heard[bus])
        self.service.request_grant(session_key(NAMES.index(bus), node), amount, lambda r: None)
        self.poll(lambda: len(self.heard[bus]) > before)

    def wait(self, us: int) -> None:
        """Move the clock on and run a loop pass (the deadlines then due)."""
        self.now += us
        self.poll(lambda: True)

    def in_c(self) -> int:
        return int(self.service.status()["frame_path_frames"])


def _scenario(tmp: Path, kind: str, fd: bool) -> tuple[dict[str, Any], Any, Any, _Run, list[int]]:
    """Every node reports; grants on both buses; on each a forged answer, a stale one and the
    genuine one, a duplicate; a grant left unanswered (sent again, then written off) and its
    late ABORTED; a replay of a COMMITTED before the session's transaction; the supervisor's
    own COMMIT replayed; a verified COMMIT it never sent; a stop, and an ACK then answered
    with ABORT. The status,
    books, state file, the run and how many frames C had taken after each bus's answers."""
    run = _Run(tmp, kind, fd)
    counts: list[int] = []
    try:
        for bus in NAMES:
            for node in NODES[bus]:
                run.answer(bus, Telemetry(node, 0), 0)
        run.grant("left", 1, 2 * J)
        run.grant("right", 1, J // 2)
        run.answer("left", Ack(1, 1), 1, flip=True)  # MAC BAD
        run.answer("right", Ack(1, 1), 0x0001_0001)  # verified, not the expected FV: stale
        counts.append(run.in_c())
        run.answer("left", Ack(1, 1), 1)  # genuine: COMMIT, on the left
        counts.append(run.in_c())
        run.answer("right", Ack(1, 1), 1)  # genuine: COMMIT, on the right
        counts.append(run.in_c())
        run.answer("right", Ack(1, 1), 1)  # a current duplicate: COMMIT again
        run.answer("left", Committed(1, 1), 1)
        run.answer("right", Committed(1, 1), 1)
        counts.append(run.in_c())
        run.grant("right", 3, J // 4)
        for _ in range(4):  # no ACK: the intention is sent again, then written off
            run.wait(1_500)
        run.answer("right", Aborted(3, 1), 1)
        counts.append(run.in_c())
        run.answer("left", Committed(1, 0), 0)  # verified, before the session's tx: stale
        commit = next(f for f in run.heard["left"] if f[0] >> 8 & 0xF == Commit.TYPE)
        at = run.heard["left"].index(commit)
        own = run.heard["left"][at : at + (1 if fd else 2)]  # with its MAC frame (classic)
        run.send("left", [can.Message(arbitration_id=i, data=d, is_fd=f) for i, d, f, _ in own])
        run.answer("left", Commit(2, 9, 1_000), 9)  # verified, an FV it never used
        run.grant("left", 2, J // 4)
        run.service.stop(run.now)  # an ACK is now answered with ABORT
        run.answer("left", Ack(2, 1), 1)
        run.answer("left", Aborted(2, 1), 1)
        counts.append(run.in_c())
        run.poll(lambda: True)
        status = run.service.status()
        books = run.service.core.state
        saved = json.loads(run.state.read_text())
    finally:
        run.close()
    return status, books, saved, run, counts


def notes(run: _Run) -> list[tuple[Any, ...]]:
    """Each bus's freshness notes: its ``FrameAuth``'s TELEMETRY floors, messages waiting for
    their MAC frames and JOINs' FVs, and the FVs its ``OwnDirection`` noted as sent."""
    out = []
    for runtime in run.built.runtimes:
        assert runtime.auth is not None and runtime.own is not None
        auth = runtime.auth
        out.append((auth.telemetry_floor, auth.pending, auth.join_fv, runtime.own.sent))
    return out


@release
@pytest.mark.parametrize("fd", [True, False], ids=["fd", "classic"])
def test_with_a_key_two_buses_on_the_c_frame_path_match_the_python_path(
    tmp_path: Path, fd: bool
) -> None:
    py_status, py_books, py_saved, py_run, py_counts = _scenario(tmp_path, "python", fd)
    c_status, c_books, c_saved, c_run, c_counts = _scenario(tmp_path, "c", fd)
    assert c_run.heard == py_run.heard  # every frame on each bus, byte for byte, in order
    for name in NAMES:
        assert all(f[2] == f[3] == fd for f in c_run.heard[name])  # FD with bit rate switch
    kinds = {n: [f[0] >> 8 & 0xF for f in c_run.heard[n] if f[0] >> 8 & 0xF] for n in NAMES}
    assert kinds["left"] == [Intention.TYPE, Commit.TYPE, Intention.TYPE, Abort.TYPE]
    assert kinds["right"] == [Intention.TYPE, Commit.TYPE] + [Intention.TYPE] * 3
    assert c_books == py_books
    assert notes(c_run) == notes(py_run)
    assert notes(c_run)[0][3] == {(1, False): 1, (2, False): 1}  # the FVs sent, left bus
    assert c_saved == py_saved and list(c_saved["sessions"]) == [
        "left/1",
        "left/2",
        "right/1",
        "right/3",
    ]
    assert (py_status["core"], py_status["frame_path"]) == ("python", "python")
    assert (c_status["core"], c_status["frame_path"]) == ("c", "c")
    assert "frame_path_off" not in c_status
    # C took no refused frame, then the genuine answers of the left bus and of the right
    assert py_counts == [0] * 6
    assert c_counts[0] == 0 and c_counts[1] == 1 and c_counts[2] == 2, c_counts
    assert c_counts[3] == 5 and c_counts[4] == 6 and c_counts[5] == 8, c_counts
    failures = c_status["auth_failures"]
    assert failures == {"MAC BAD": 1, "freshness not the expected one": 3}, failures
    assert c_status["buses"]["left"]["auth_failures"] == {
        "MAC BAD": 1,
        "freshness not the expected one": 2,
    }
    assert c_status["buses"]["right"]["auth_failures"] == {"freshness not the expected one": 1}
    reasons = c_status["refused"]["by_node"]["left/1"]["reasons"]
    assert reasons["freshness not the expected one (in the supervisor's direction)"]["count"] == 1
    assert c_status["nodes"]["left/2"]["intrusions"] == 1  # the COMMIT it never sent
    left2 = session_key(0, 2)
    assert c_run.service.intrusions.authentic_by_node == {left2: 1}
    assert py_run.service.intrusions.authentic_by_node == {left2: 1}
    assert c_status["nodes"]["right/1"]["committed_uj"] == J // 2
    assert c_status["nodes"]["right/3"]["written_off"] == 1
    assert c_status["nodes"]["left/2"]["aborted"] == 1
    assert py_status["frame_path_off"] == "with a key the bus loop verifies and decodes each frame"
    for key in CHANGES:
        py_status.pop(key, None), c_status.pop(key, None)
    assert c_status == py_status


# -- any run, frame for frame: the builder's runtimes driven one pass at a time ----------------


class _Wire(can.BusABC):
    """An in-memory bus end: what is sent is kept whole (FD flags too). It receives nothing:
    the test hands each frame to the bus's runtime itself."""

    def __init__(self) -> None:
        super().__init__(channel="wire")
        self.sent: list[tuple[int, bytes, bool, bool]] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(frame_key(msg))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        time.sleep(min(timeout or 0.0, 0.005))  # the builder's reader threads, until closed
        return None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


class _Side:
    """A supervisor with a key over two in-memory buses, built by ``build_supervisor`` (the
    Python core on the usual path, or the compiled core, on the tests' UBSan build, on its
    frame path); its runtimes are handed each pass's frames as ``BusGroup.poll`` hands them."""

    def __init__(self, tmp: Path, c: bool, fd: bool) -> None:
        self.now = 1_000_000
        self.wires = [_Wire(), _Wire()]
        self.state = tmp / f"{'c' if c else 'python'}-{uuid.uuid4().hex}.json"
        core: SupervisorCore
        if c:
            from support.c_binding import library

            from canergy.ccore.buses import CompiledBuses

            core = CompiledBuses(KEYS, 10**9, timing=T, module=library().module)
        else:
            core = make_supervisor("python", KEYS, 10**9, timing=T, buses=True)
        config = SupervisorConfig(
            service=ServiceConfig(state_path=self.state, fsync=False, bus_names=NAMES),
            auth=AuthConfig(MASTERS[0], fd=fd, bus_keys=MASTERS),
        )
        self.built: RunningSupervisor = build_supervisor(
            config, self.wires, core=core, clock=lambda: self.now
        )
        self.built.loop.close()  # its reader threads: the test hands the frames over itself
        self.service = self.built.service

    def step(self, now: int, frames: list[tuple[int, can.Message]]) -> None:
        """One loop pass at ``now`` over every bus: ``frames`` (bus index, frame) received in
        order, then what is due."""
        self.now = now
        runtimes = self.built.runtimes
        for runtime in runtimes:
            runtime.begin_pass()
        try:
            for bus, frame in frames:
                runtimes[bus].receive(copy.copy(frame))
            for runtime in runtimes:
                runtime.run_due()
        finally:
            for runtime in runtimes:
                runtime.end_pass()

    def seen(self) -> tuple[Any, ...]:
        status = self.service.status()
        for key in CHANGES:
            status.pop(key, None)
        notes = []
        for runtime in self.built.runtimes:
            assert runtime.auth is not None and runtime.own is not None
            auth = runtime.auth
            notes.append((auth.telemetry_floor, auth.pending, auth.join_fv, runtime.own.sent))
        return (
            [wire.sent for wire in self.wires],
            self.service.core.state,
            status,
            copy.deepcopy(notes),
            dict(self.service.intrusions.authentic_by_node),
            self.state.read_text() if self.state.exists() else None,
        )

    def close(self) -> None:
        self.built.close()
        for wire in self.wires:
            wire.shutdown()


_HOW = ["genuine"] * 8 + ["flip", "high", "mac-less", "lone-mac", "cut", "split", "other-key"]
"""How an answer is sent; ``other-key``: signed under the other bus's key (refused)."""
_ANSWER = st.tuples(
    st.sampled_from([0, 1]),  # the bus it is sent on
    st.sampled_from([False, False, False, True]),  # its counters: the other bus's session's
    st.sampled_from([1, 1, 2, 3, 7]),
    st.sampled_from([Ack, Committed, Aborted]),
    st.sampled_from([0, 0, 0, -1, -2, 1]),  # the transaction named, from the session's
    st.sampled_from(_HOW),
)
_STEP = st.one_of(
    st.tuples(st.just("grant"), st.sampled_from(KEYS), st.integers(1, 3)),
    st.tuples(st.just("pass"), st.lists(_ANSWER, min_size=1, max_size=3)),
    st.tuples(st.just("pass"), st.lists(_ANSWER, min_size=1, max_size=3)),
    st.tuples(st.just("pass"), st.lists(_ANSWER, min_size=1, max_size=3)),
    st.tuples(st.just("telemetry"), st.sampled_from(KEYS)),
    st.tuples(st.just("wait"), st.integers(100, 3_000)),
    st.tuples(st.just("stop")),
)


def _answer(
    ref: _Side, fd: bool, answer: tuple[Any, ...]
) -> tuple[list[tuple[int, can.Message]], list[tuple[int, can.Message]]]:
    """One answer's frames for this pass and for the next, each with its bus."""
    bus, other, node, kind, offset, how = answer
    key = session_key(1 - bus if other else bus, node)
    tx = max(0, (ref.service.core.session(key).tx if key in KEYS else 1) + offset)
    msg = kind(node, tx & 0xFFFF)
    if how == "mac-less":
        ident, data = CODEC.encode(msg)
        return [(bus, can.Message(arbitration_id=ident, data=data))], []
    fv = tx | (0x1_0000 if how == "high" else 0)
    frames = signed(msg, fv, fd, 1 - bus if how == "other-key" else bus, flip=how == "flip")
    if fd:
        return [(bus, frames[0])], []
    data, mac = frames
    if how == "lone-mac":
        return [(bus, mac)], []
    if how == "cut":
        return [
            (bus, data),
            (bus, can.Message(arbitration_id=mac.arbitration_id, data=mac.data[:7])),
        ], []
    if how == "split":  # its MAC frame a pass later
        return [(bus, data)], [(bus, mac)]
    return [(bus, data), (bus, mac)], []


def _side_by_side(fd: bool, steps: list[Any]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        ref, c = _Side(Path(tmp), False, fd), _Side(Path(tmp), True, fd)
        try:
            now = 1_000_000
            for side in (ref, c):  # every node heard: grants may begin
                side.step(
                    now,
                    [
                        (k >> 8, f)
                        for k in KEYS
                        for f in signed(Telemetry(k & 0xFF, 0), 0, fd, k >> 8)
                    ],
                )
            later: list[tuple[int, can.Message]] = []
            for step in steps:
                now += 100
                frames, later = later, []
                if step[0] == "grant":
                    for side in (ref, c):
                        side.service.request_grant(step[1], step[2] * J, lambda reply: None)
                elif step[0] == "pass":
                    for answer in step[1]:
                        now_frames, next_frames = _answer(ref, fd, answer)
                        frames += now_frames
                        later += next_frames
                elif step[0] == "telemetry":
                    key = step[1]
                    tx = ref.service.core.session(key).tx
                    telemetry = Telemetry(key & 0xFF, 500)
                    frames += [(key >> 8, f) for f in signed(telemetry, tx, fd, key >> 8)]
                elif step[0] == "wait":
                    now += step[1]
                else:
                    for side in (ref, c):
                        side.service.stop(now)
                for side in (ref, c):
                    side.step(now, frames)
                assert c.seen() == ref.seen()
            assert ref.service.frames_in_c == 0
            assert c.service.status()["frame_path"] == "c"
            event(f"answers taken in C: {min(c.service.frames_in_c, 4)}+")
        finally:
            ref.close()
            c.close()


@release
@settings(max_examples=60, deadline=None)
@given(st.lists(_STEP, min_size=5, max_size=40))
def test_fd_frame_for_frame_two_buses_on_the_c_path_with_a_key_are_the_python_path(
    steps: list[Any],
) -> None:
    """Any run of grants, passes of answers on either bus or both (genuine, forged, with a
    foreign FV high half, without a MAC, under the other bus's key, with the counters of the
    other bus's session of the same node or of a node the bus does not have), TELEMETRY, waits
    and a stop: after every pass both sides sent the same bytes on each bus and hold the same
    books, state file, status, freshness notes and evidence."""
    _side_by_side(True, steps)


@release
@settings(max_examples=60, deadline=None)
@given(st.lists(_STEP, min_size=5, max_size=40))
def test_classic_frame_for_frame_two_buses_on_the_c_path_with_a_key_are_the_python_path(
    steps: list[Any],
) -> None:
    """``test_fd_...`` in the classic layout, with what only it goes through: a MAC frame
    without its message, one cut short, a message whose MAC frame comes a pass later (the
    other bus's frames between them), each bus's messages waiting for their MAC frames apart."""
    _side_by_side(False, steps)


# -- each bus's supervisor in C verifies under its own bus's keys -------------------------------


@release
@pytest.mark.parametrize("fd", [True, False], ids=["fd", "classic"])
def test_each_bus_in_c_verifies_and_signs_under_the_keys_its_bus_was_given(fd: bool) -> None:
    """``CompiledBuses.use_keys(bus=)``: each bus's supervisor holds the keys its bus's
    ``FrameAuth`` was given. An INTENTION to node 1 of the right bus is signed under the right
    bus's key; an ACK (and a COMMITTED) signed under the left bus's key is refused there, one
    under the right bus's taken by the right bus's session and reported keyed by it."""
    from canergy.ccore.buses import CompiledBuses
    from canergy.core.actions import Resolved
    from canergy.core.state import Phase

    def keys(bus: int) -> Callable[[int], bytes]:
        return lambda node: bytes([node | bus << 6]) * 16

    core = CompiledBuses(KEYS, 10 * J, timing=T)
    for bus in (0, 1):
        core.use_keys(keys(bus), classic=not fd, bus=bus)
    right1 = session_key(1, 1)
    _, frames = core.begin_protected(right1, J, 0)
    layout = Layout.FD if fd else Layout.CLASSIC

    def signed_under(bus: int, msg: Message, receives: Direction) -> list[tuple[int, bytes]]:
        auth = FrameAuth(CODEC, layout, keys(bus), receives, lambda m: 1)
        return [(f.arbitration_id, bytes(f.data)) for f in auth.frames(msg)]

    intention = Intention(1, 1, 1_000, 0)
    assert frames == signed_under(1, intention, Direction.TO_SUPERVISOR)
    assert frames != signed_under(0, intention, Direction.TO_SUPERVISOR)

    def answer(msg: Message, key: int, on: int) -> tuple[int, list[Any]]:
        """``msg`` signed under bus ``key``'s keys, on bus ``on``."""
        sent = signed_under(key, msg, Direction.TO_CLIENT)
        if fd:
            status, actions, _, _ = core.auth_answer_on(on)(*sent[0], True, False, 100, False)
        else:
            (data_id, data), (mac_id, mac) = sent
            pair = core.auth_pair_on(on)
            status, actions, _, _ = pair(data_id, data, mac_id, mac, True, False, 100, False)
        return status, actions

    assert answer(Ack(1, 1), 0, 1)[0] != 0 and core.session(right1).phase is Phase.WAIT_ACK
    assert answer(Ack(1, 1), 1, 1)[0] == 0 and core.session(right1).phase is Phase.WAIT_CONFIRM
    assert answer(Committed(1, 1), 0, 1)[0] != 0
    status, actions = answer(Committed(1, 1), 1, 1)
    assert status == 0 and [a.node for a in actions if isinstance(a, Resolved)] == [right1]
    assert core.session(right1).delivered == J and core.session(session_key(0, 1)).tx == 0
    left1 = session_key(0, 1)  # and the left bus's node 1 under the left bus's keys only
    assert core.begin_protected(left1, J, 200)[1] == signed_under(
        0, intention, Direction.TO_SUPERVISOR
    )
    assert answer(Ack(1, 1), 1, 0)[0] != 0 and core.session(left1).phase is Phase.WAIT_ACK
    assert answer(Ack(1, 1), 0, 0)[0] == 0 and core.session(left1).phase is Phase.WAIT_CONFIRM
