"""The compiled core's frame path with a key (``--auth``, FD layout): the same frames through a
service on the usual path (Python verifies, the rules run, Python signs) and through one whose
bus loop hands ACK, COMMITTED and ABORTED to C (verified, ruled and protected in one call) send
the same bytes, keep the same books and refuse the same frames for the same reasons."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import can
from hypothesis import event, given, settings
from hypothesis import strategies as st
from support.ccore_built import release

from canergy.auth.frames import FrameAuth, Layout
from canergy.ccore.supervisor import make_supervisor
from canergy.codec import Codec
from canergy.core.timing import Timing
from canergy.live.runtime import BusRuntime
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
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

T = Timing(response_timeout_us=1_000, retries=2)
CODEC = Codec()


def key_for(node: int) -> bytes:
    return bytes([node]) * 16


class _Wire(can.BusABC):
    """An in-memory bus end: what is sent is kept whole (FD flags too), what is queued is
    received."""

    def __init__(self) -> None:
        super().__init__(channel="wire")
        self.inbox: list[can.Message] = []
        self.sent: list[tuple[int, bytes, bool, bool]] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((msg.arbitration_id, bytes(msg.data), msg.is_fd, msg.bitrate_switch))

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.pop(0) if self.inbox else None), False


def signed(msg: Message, fv: int, *, flip: bool = False) -> can.Message:
    """``msg`` in the FD layout with freshness value ``fv`` under its node's key; ``flip``:
    one bit of its MAC flipped."""
    frame = FrameAuth(CODEC, Layout.FD, key_for, Direction.TO_CLIENT, lambda m: fv).frames(msg)[0]
    if flip:
        frame.data[-1] ^= 0x01
    return frame


@dataclass
class Run:
    sent: list[tuple[int, bytes, bool, bool]]
    status: dict[str, Any]
    service: SupervisorService
    loop: BusRuntime


def _run(core: str, frame_path: bool) -> Run:
    """The script: grants, genuine, replayed, forged and stale answers, another node's ACK,
    an ABORTED after a write-off, an ACK answered with ABORT (stopping), frames in the
    supervisor's own direction (a replay of the COMMIT it sent, a verified one it never
    sent)."""
    wire, now = _Wire(), [0]
    service = build_service(make_supervisor(core, [3, 5], 10_000_000, timing=T), ServiceConfig(), 0)
    auth = FrameAuth(CODEC, Layout.FD, key_for, Direction.TO_SUPERVISOR, service.freshness)
    path = service.frame_path(None, auth) if frame_path else None
    loop = BusRuntime(
        wire,
        service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        auth=auth,
        frame_path=path,
        counters=service.bus_counters,
        clock=lambda: now[0],
    )

    def feed(*frames: can.Message, wait: int = 100) -> None:
        for frame in frames:
            now[0] += wait
            wire.inbox.append(frame)
            loop.poll(0)

    def grant(node: int, amount: int) -> None:
        service.request_grant(node, amount, lambda reply: None)
        now[0] += 100
        loop.poll(0)

    feed(signed(Telemetry(3, 0), 0), signed(Telemetry(5, 0), 0))
    grant(3, 2_000_000)
    feed(
        signed(Ack(3, 1), 1, flip=True),  # MAC BAD
        signed(Ack(3, 1), 0x0001_0001),  # verified, an FV not the expected one: stale
        signed(Ack(3, 1), 1),  # genuine: COMMIT
        signed(Ack(3, 1), 1),  # a current duplicate: taken as the rules take it
        signed(Ack(7, 1), 1),  # a node this supervisor does not manage
        signed(Committed(3, 1), 1),
        signed(Telemetry(3, 2_000), 1),
    )
    commit = next(f for f in wire.sent if f[0] >> 8 & 0xF == Commit.TYPE)
    grant(3, 1_000_000)
    for _ in range(4):  # no ACK: the intention is sent again, then aborted
        now[0] += 1_500
        loop.poll(0)
    feed(
        signed(Aborted(3, 2), 2),
        signed(Committed(3, 1), 1),  # verified, before the session's tx: a replay, stale
        can.Message(arbitration_id=commit[0], data=commit[1], is_fd=True),  # its own COMMIT
        signed(Commit(3, 9, 1_000), 9),  # verified, an FV it never used: a second supervisor
    )
    grant(5, 1_000_000)
    feed(signed(Ack(5, 1), 1), signed(Committed(5, 1), 1), signed(Telemetry(5, 1_000), 1))
    grant(5, 1_000_000)
    service.stop(now[0])  # an ACK is now answered with ABORT
    feed(signed(Ack(5, 2), 2), signed(Aborted(5, 2), 2))
    wire.shutdown()
    return Run(wire.sent, service.status(), service, loop)


_SAME = (
    "usable_uj",
    "reserved_uj",
    "delivered_uj",
    "intrusions",
    "nodes",
    "frames_sent",
    "frames_received",
    "auth_failures",
    "decode_errors",
    "refused",
)


@release
def test_with_a_key_the_c_frame_path_answers_as_the_python_path_does() -> None:
    """Frame for frame the same bytes (FD, bit rate switch) and books; the same refusals by
    reason (MAC BAD, the stale ACK, the replayed COMMITTED, the replay of its own COMMIT), the
    same authentic intrusion (a verified COMMIT it never sent); the same freshness notes
    (TELEMETRY floors, the FVs it sent). The C run took every genuine answer in C."""
    ref = _run("python", False)
    c = _run("c", True)
    assert c.sent == ref.sent
    kinds = [ident >> 8 & 0xF for ident, *_ in c.sent]
    assert (kinds.count(Commit.TYPE), kinds.count(Abort.TYPE)) == (2, 1)
    assert all(is_fd and brs for _, _, is_fd, brs in c.sent)
    for key in _SAME:
        assert c.status.get(key) == ref.status.get(key), key
    failures = c.status["auth_failures"]
    assert failures == {"MAC BAD": 1, "freshness not the expected one": 3}, failures
    reasons = c.status["refused"]["by_node"]["3"]["reasons"]
    assert reasons["freshness not the expected one (in the supervisor's direction)"]["count"] == 1
    assert c.service.intrusions.authentic_by_node == {3: 1}  # the COMMIT it never sent
    assert ref.service.intrusions.authentic_by_node == {3: 1}
    assert c.service.core.state == ref.service.core.state
    assert c.loop.auth is not None and ref.loop.auth is not None
    assert c.loop.auth.telemetry_floor == ref.loop.auth.telemetry_floor == {3: 2, 5: 2}
    assert c.loop.own is not None and ref.loop.own is not None
    assert c.loop.own.sent == ref.loop.own.sent == {(3, False): 2, (5, False): 2}
    assert (ref.status["frame_path"], c.status["frame_path"]) == ("python", "c")
    # node 3's genuine ACK and its duplicate, COMMITTED, ABORTED; node 5's two ACKs, COMMITTED,
    # ABORTED: the rest (refused, TELEMETRY, another node's, its own direction) on the usual path
    assert (ref.status["frame_path_frames"], c.status["frame_path_frames"]) == (0, 8)


@release
def test_what_the_c_frame_path_sends_is_the_supervisors_own_from_then_on() -> None:
    """A COMMIT the C path protected and sent is noted as this side's (``OwnDirection``): its
    replay is refused as stale, never taken as a second supervisor's; a verified COMMIT with an
    FV it never used is authentic evidence."""
    wire, now = _Wire(), [0]
    service = build_service(make_supervisor("c", [3], 10_000_000, timing=T), ServiceConfig(), 0)
    auth = FrameAuth(CODEC, Layout.FD, key_for, Direction.TO_SUPERVISOR, service.freshness)
    loop = BusRuntime(
        wire,
        service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        auth=auth,
        frame_path=service.frame_path(None, auth),
        counters=service.bus_counters,
        clock=lambda: now[0],
    )
    service.on_message(Telemetry(3, 0), 0)
    service.request_grant(3, 2_000_000, lambda reply: None)
    loop.poll(0)
    assert loop.own is not None
    loop.own.sent.clear()  # what the INTENTION noted: the COMMIT alone notes it again below
    wire.inbox.append(signed(Ack(3, 1), 1))
    loop.poll(0)
    assert service.frames_in_c == 1 and loop.own.sent == {(3, False): 1}
    ident, data, fd, _ = wire.sent[-1]
    assert ident >> 8 & 0xF == Commit.TYPE and fd
    wire.inbox += [
        can.Message(arbitration_id=ident, data=data, is_fd=True),
        signed(Commit(3, 2, 1_000), 2),
    ]
    loop.poll(0)
    reasons = service.status()["refused"]["by_node"]["3"]["reasons"]
    assert list(reasons) == ["freshness not the expected one (in the supervisor's direction)"]
    assert service.intrusions.authentic_by_node == {3: 1}
    wire.shutdown()


@release
def test_a_guarded_drives_intention_protected_in_c_reaches_its_proxy_as_the_message() -> None:
    """With ``--cia402`` a proxied drive's INTENTION never goes on the bus: the one C protected
    (FD: the message, padding, FV, MAC) is handed to the proxy as the message it carries."""
    from types import SimpleNamespace

    from canergy.ccore.supervisor import CompiledSupervisor
    from canergy.live.canopen.cia402_host import GuardedSupervisor
    from canergy.live.runtime import RawFrame
    from canergy.messages import Intention

    core = CompiledSupervisor([3], 10_000_000, timing=T)
    core.use_keys(key_for)
    _, frames = core.begin_protected(3, 2_000_000, 0)
    (ident, data), routed = frames[0], []
    assert len(data) == 20
    service = SimpleNamespace(now=0, end_pass=lambda: [RawFrame(ident, data, True)])
    host = GuardedSupervisor(service, SimpleNamespace(guards=lambda node: True))  # type: ignore[arg-type]
    host._route = lambda msgs, now: routed.extend(msgs) or []  # type: ignore[method-assign]
    assert host.end_pass() == [] and routed == [Intention(3, 1, 2_000, 0)]


class _Side:
    """A service and its bus loop on one path (reference: the Python core, usual path; or the
    compiled core's frame path with the key), on a clock the test drives."""

    def __init__(self, c_path: bool) -> None:
        self.wire, self.now = _Wire(), 0
        core = make_supervisor("c" if c_path else "python", [3, 5], 10**9, timing=T)
        self.service = build_service(core, ServiceConfig(), 0)
        auth = FrameAuth(CODEC, Layout.FD, key_for, Direction.TO_SUPERVISOR, self.service.freshness)
        self.loop = BusRuntime(
            self.wire,
            self.service,
            codec=CODEC,
            receives=Direction.TO_SUPERVISOR,
            auth=auth,
            frame_path=self.service.frame_path(None, auth) if c_path else None,
            counters=self.service.bus_counters,
            clock=lambda: self.now,
        )
        for node in (3, 5):  # heard: grants may begin
            self.step(0, signed(Telemetry(node, 0), 0))

    def step(self, now: int, frame: can.Message | None = None) -> None:
        self.now = now
        if frame is not None:
            self.wire.inbox.append(frame)
        self.loop.poll(0)

    def seen(self) -> tuple[Any, ...]:
        status = self.service.status()
        assert self.loop.auth is not None and self.loop.own is not None
        return (
            self.wire.sent,
            self.service.core.state,
            {key: status.get(key) for key in _SAME},
            dict(self.loop.auth.telemetry_floor),
            dict(self.loop.own.sent),
            dict(self.service.intrusions.authentic_by_node),
        )


_ANSWERS = (Ack, Committed, Aborted)


_ANSWER = st.tuples(
    st.just("answer"),
    st.sampled_from([3, 3, 5, 7]),
    st.sampled_from(_ANSWERS),
    st.sampled_from([0, 0, 0, -1, -2, 1]),  # the transaction named, from the session's
    st.sampled_from(["genuine"] * 5 + ["flip", "high", "mac-less"]),
)
_STEP = st.one_of(
    st.tuples(st.just("grant"), st.sampled_from([3, 5]), st.integers(1, 3)),
    _ANSWER,
    _ANSWER,
    _ANSWER,
    st.tuples(st.just("wait"), st.integers(100, 3_000)),
    st.tuples(st.just("grant"), st.just(3), st.just(1)),
    _ANSWER,
    _ANSWER,
    st.tuples(st.just("stop")),
)


@release
@settings(max_examples=80, deadline=None)
@given(st.lists(_STEP, min_size=5, max_size=40))
def test_frame_for_frame_the_c_path_with_a_key_is_the_python_path(steps: list[Any]) -> None:
    """Any run of grants, answers (genuine, forged, with a foreign FV high half, without a MAC,
    naming the session's transaction or a neighbour), waits and a stop: after every step both
    sides sent the same bytes and hold the same books, refusals, freshness notes and evidence."""
    ref, c = _Side(False), _Side(True)
    now = 0
    for step in steps:
        now += 100
        frame = None
        if step[0] == "grant":
            for side in (ref, c):
                side.service.request_grant(step[1], step[2] * 1_000_000, lambda reply: None)
        elif step[0] == "answer":
            _, node, kind, offset, how = step
            tx = max(0, (ref.service.core.session(node).tx if node != 7 else 1) + offset)
            msg = kind(node, tx & 0xFFFF)
            if how == "mac-less":
                arbitration_id, data = CODEC.encode(msg)
                frame = can.Message(arbitration_id=arbitration_id, data=data)
            else:
                frame = signed(msg, tx | (0x1_0000 if how == "high" else 0), flip=how == "flip")
        elif step[0] == "wait":
            now += step[1]
        else:
            for side in (ref, c):
                side.service.stop(now)
        for side in (ref, c):
            side.step(now, None if frame is None else copy.copy(frame))
        assert c.seen() == ref.seen()
    ref.wire.shutdown()
    c.wire.shutdown()
    assert ref.service.frames_in_c == 0 and c.service.status()["frame_path"] == "c"
    event(f"answers taken in C: {min(c.service.frames_in_c, 3)}+")


# -- the classic layout: a message, then its MAC frame -------------------------------------------


def classic(msg: Message, fv: int, *, flip: bool = False) -> list[can.Message]:
    """``msg`` in the classic layout with freshness value ``fv`` under its node's key: the data
    frame, then its MAC frame (``flip``: one bit of its MAC flipped)."""
    frames = FrameAuth(CODEC, Layout.CLASSIC, key_for, Direction.TO_CLIENT, lambda m: fv).frames(
        msg
    )
    if flip:
        frames[1].data[-1] ^= 0x01
    return frames


def _classic_run(core: str, frame_path: bool) -> Run:
    """``_run``'s script in the classic layout, with what only it can go through: a MAC frame
    without its message, a message replaced before its MAC frame, a MAC frame cut short, one
    for another type, a message whose MAC frame comes a pass later, an answer ahead of the
    session (verified, then judged by the rules), its own COMMIT and a COMMIT it never sent
    (both a data frame and its MAC frame)."""
    wire, now = _Wire(), [0]
    service = build_service(make_supervisor(core, [3, 5], 10_000_000, timing=T), ServiceConfig(), 0)
    auth = FrameAuth(CODEC, Layout.CLASSIC, key_for, Direction.TO_SUPERVISOR, service.freshness)
    loop = BusRuntime(
        wire,
        service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        auth=auth,
        frame_path=service.frame_path(None, auth) if frame_path else None,
        counters=service.bus_counters,
        clock=lambda: now[0],
    )

    def feed(*frames: can.Message, wait: int = 100) -> None:
        now[0] += wait
        wire.inbox.extend(frames)
        loop.poll(0)

    def grant(node: int, amount: int) -> None:
        service.request_grant(node, amount, lambda reply: None)
        now[0] += 100
        loop.poll(0)

    feed(*classic(Telemetry(3, 0), 0), *classic(Telemetry(5, 0), 0))
    grant(3, 2_000_000)
    ack, mac = classic(Ack(3, 1), 1)
    feed(
        *classic(Ack(3, 1), 1, flip=True),  # MAC BAD
        *classic(Ack(3, 1), 0x0001_0001),  # verified, an FV not the expected one: stale
        mac,  # a MAC frame without its message
        ack,
        classic(Committed(3, 1), 1)[1],  # a MAC frame of another type: without its message
        ack,
        can.Message(arbitration_id=mac.arbitration_id, data=mac.data[:5]),  # cut short
        ack,
        ack,  # replaced before its MAC frame: the first is counted without a MAC
        mac,  # the genuine pair: COMMIT
    )
    feed(ack)
    feed(mac)  # a current duplicate, its MAC frame a pass later
    feed(*classic(Ack(7, 1), 1), *classic(Committed(3, 1), 1), *classic(Telemetry(3, 2_000), 1))
    feed(*classic(Ack(3, 2), 2))  # ahead of the session: verified, then the rules' to judge
    commit = next(i for i, f in enumerate(wire.sent) if f[0] >> 8 & 0xF == Commit.TYPE)
    grant(3, 1_000_000)
    for _ in range(4):  # no ACK: the intention is sent again, then aborted
        now[0] += 1_500
        loop.poll(0)
    feed(
        *classic(Aborted(3, 2), 2),
        *classic(Committed(3, 1), 1),  # verified, before the session's tx: a replay, stale
        *(can.Message(arbitration_id=i, data=d) for i, d, *_ in wire.sent[commit : commit + 2]),
        *classic(Commit(3, 9, 1_000), 9),  # verified, an FV it never used: a second supervisor
    )
    grant(5, 1_000_000)
    feed(*classic(Ack(5, 1), 1), *classic(Committed(5, 1), 1), *classic(Telemetry(5, 1_000), 1))
    grant(5, 1_000_000)
    service.stop(now[0])  # an ACK is now answered with ABORT
    feed(*classic(Ack(5, 2), 2), *classic(Aborted(5, 2), 2))
    wire.shutdown()
    return Run(wire.sent, service.status(), service, loop)


@release
def test_classic_with_a_key_the_c_frame_path_answers_as_the_python_path_does() -> None:
    """The classic layout through C (the pair verified, ruled and answered in one call) and
    through Python: frame for frame the same bytes (classic frames, each followed by its MAC
    frame) and books, the same refusals by reason, the same intrusions and freshness notes.
    The C run took every genuine answer in C: the classic layout does not fall back."""
    ref = _classic_run("python", False)
    c = _classic_run("c", True)
    assert c.sent == ref.sent
    kinds = [ident >> 8 & 0xF for ident, *_ in c.sent]
    assert (kinds.count(Commit.TYPE), kinds.count(Abort.TYPE)) == (2, 1)
    assert kinds.count(0x0) == len(kinds) // 2  # a MAC frame after each
    assert not any(is_fd or brs for _, _, is_fd, brs in c.sent)
    for key in (*_SAME, "sessions"):
        assert c.status.get(key) == ref.status.get(key), key
    failures = c.status["auth_failures"]
    assert failures == {
        "MAC BAD": 1,
        "freshness not the expected one": 3,
        "MAC frame without its message": 2,
        "malformed authenticated frame": 1,
        "frame without a MAC": 1,
    }, failures
    reasons = c.status["refused"]["by_node"]["3"]["reasons"]
    assert reasons["freshness not the expected one (in the supervisor's direction)"]["count"] == 1
    assert c.service.intrusions.authentic_by_node == {3: 1}  # the COMMIT it never sent
    assert ref.service.intrusions.authentic_by_node == {3: 1}
    assert c.status["intrusions"] == ref.status["intrusions"] and c.status["intrusions"]
    assert c.service.core.state == ref.service.core.state
    assert c.loop.auth is not None and ref.loop.auth is not None
    assert c.loop.auth.telemetry_floor == ref.loop.auth.telemetry_floor == {3: 2, 5: 2}
    assert c.loop.auth.pending == ref.loop.auth.pending == {}
    assert c.loop.own is not None and ref.loop.own is not None
    assert c.loop.own.sent == ref.loop.own.sent == {(3, False): 2, (5, False): 2}
    assert (ref.status["frame_path"], c.status["frame_path"]) == ("python", "c")
    assert "frame_path_off" not in c.status
    # node 3's genuine ACK and its duplicate, COMMITTED, ABORTED; node 5's two ACKs, COMMITTED,
    # ABORTED: the rest (refused, TELEMETRY, the ACK ahead, another node's) on the usual path
    assert (ref.status["frame_path_frames"], c.status["frame_path_frames"]) == (0, 8)


@release
def test_classic_what_the_c_frame_path_sends_is_the_supervisors_own_from_then_on() -> None:
    """An INTENTION and a COMMIT C protected in the classic layout are what Python's
    ``FrameAuth`` sends, byte for byte, and noted as this side's: the COMMIT's replay is
    refused as stale; a verified COMMIT with an FV it never used is authentic evidence."""
    wire, now = _Wire(), [0]
    service = build_service(make_supervisor("c", [3], 10_000_000, timing=T), ServiceConfig(), 0)
    auth = FrameAuth(CODEC, Layout.CLASSIC, key_for, Direction.TO_SUPERVISOR, service.freshness)
    loop = BusRuntime(
        wire,
        service,
        codec=CODEC,
        receives=Direction.TO_SUPERVISOR,
        auth=auth,
        frame_path=service.frame_path(None, auth),
        counters=service.bus_counters,
        clock=lambda: now[0],
    )
    service.on_message(Telemetry(3, 0), 0)
    service.request_grant(3, 2_000_000, lambda reply: None)
    loop.poll(0)
    python = FrameAuth(CODEC, Layout.CLASSIC, key_for, Direction.TO_SUPERVISOR, lambda m: 1)
    as_sent = [(f.arbitration_id, bytes(f.data), False, False) for f in python.frames(
        Intention(3, 1, 2_000, 0)
    )]  # fmt: skip
    assert wire.sent == as_sent
    assert loop.own is not None and loop.own.sent == {(3, False): 1}
    loop.own.sent.clear()  # what the INTENTION noted: the COMMIT alone notes it again below
    wire.inbox += classic(Ack(3, 1), 1)
    loop.poll(0)
    assert service.frames_in_c == 1 and loop.own.sent == {(3, False): 1}
    as_sent = [(f.arbitration_id, bytes(f.data), False, False) for f in python.frames(
        Commit(3, 1, 2_000)
    )]  # fmt: skip
    assert wire.sent[-2:] == as_sent
    wire.inbox += [can.Message(arbitration_id=i, data=d) for i, d, *_ in as_sent]
    wire.inbox += classic(Commit(3, 2, 1_000), 2)
    loop.poll(0)
    reasons = service.status()["refused"]["by_node"]["3"]["reasons"]
    assert list(reasons) == ["freshness not the expected one (in the supervisor's direction)"]
    assert service.intrusions.authentic_by_node == {3: 1}
    wire.shutdown()


@release
def test_classic_a_guarded_drives_intention_protected_in_c_reaches_its_proxy_once() -> None:
    """With ``--cia402`` and the classic layout, a proxied drive's INTENTION C protected (the
    message, then its MAC frame) reaches the proxy once, as the message; neither frame goes on
    the bus."""
    from types import SimpleNamespace

    from canergy.ccore.supervisor import CompiledSupervisor
    from canergy.live.canopen.cia402_host import GuardedSupervisor
    from canergy.live.runtime import RawFrame

    core = CompiledSupervisor([3], 10_000_000, timing=T)
    core.use_keys(key_for, classic=True)
    _, frames = core.begin_protected(3, 2_000_000, 0)
    python = FrameAuth(CODEC, Layout.CLASSIC, key_for, Direction.TO_SUPERVISOR, lambda m: 1)
    intention = Intention(3, 1, 2_000, 0)
    assert frames == [(f.arbitration_id, bytes(f.data)) for f in python.frames(intention)]
    routed: list[Message] = []
    held = [RawFrame(i, d) for i, d in frames]
    service = SimpleNamespace(now=0, end_pass=lambda: held)
    host = GuardedSupervisor(service, SimpleNamespace(guards=lambda node: True))  # type: ignore[arg-type]
    host._route = lambda msgs, now: routed.extend(msgs) or []  # type: ignore[method-assign]
    assert host.end_pass() == [] and routed == [intention]


class _ClassicSide(_Side):
    """``_Side`` in the classic layout; the compiled core on the tests' UBSan build
    (tests/support/c_binding.py), so that undefined behaviour in the C pairing aborts."""

    def __init__(self, c_path: bool) -> None:
        from support.c_binding import compiled_core

        self.wire, self.now = _Wire(), 0
        core: Any = (
            compiled_core([3, 5], 10**9, timing=T)
            if c_path
            else make_supervisor("python", [3, 5], 10**9, timing=T)
        )
        self.service = build_service(core, ServiceConfig(), 0)
        auth = FrameAuth(
            CODEC, Layout.CLASSIC, key_for, Direction.TO_SUPERVISOR, self.service.freshness
        )
        self.loop = BusRuntime(
            self.wire,
            self.service,
            codec=CODEC,
            receives=Direction.TO_SUPERVISOR,
            auth=auth,
            frame_path=self.service.frame_path(None, auth) if c_path else None,
            counters=self.service.bus_counters,
            clock=lambda: self.now,
        )
        for node in (3, 5):  # heard: grants may begin
            for frame in classic(Telemetry(node, 0), 0):
                self.step(0, frame)

    def seen(self) -> tuple[Any, ...]:
        assert self.loop.auth is not None
        return (*super().seen(), dict(self.loop.auth.pending))


_HOW = ["genuine"] * 8 + ["flip", "high", "mac-less", "lone-mac", "replaced", "cut", "split"]
_CLASSIC_ANSWER = st.tuples(
    st.just("answer"),
    st.sampled_from([3, 3, 5, 7]),
    st.sampled_from(_ANSWERS),
    st.sampled_from([0, 0, 0, -1, -2, 1]),
    st.sampled_from(_HOW),
)
_CLASSIC_STEP = st.one_of(
    st.tuples(st.just("grant"), st.sampled_from([3, 5]), st.integers(1, 3)),
    _CLASSIC_ANSWER,
    _CLASSIC_ANSWER,
    _CLASSIC_ANSWER,
    st.tuples(st.just("wait"), st.integers(100, 3_000)),
    _CLASSIC_ANSWER,
    st.tuples(st.just("stop")),
)


@release
@settings(max_examples=80, deadline=None)
@given(st.lists(_CLASSIC_STEP, min_size=5, max_size=40))
def test_classic_frame_for_frame_the_c_path_with_a_key_is_the_python_path(steps: list[Any]) -> None:
    """Any run of grants, answers (genuine, forged, with a foreign FV high half, a message
    without its MAC frame, a MAC frame without its message, a message replaced before its MAC
    frame, a MAC frame cut short, a pair split over two passes), waits and a stop: after every
    pass both sides sent the same bytes and hold the same books, refusals, freshness notes,
    waiting messages and evidence."""
    ref, c = _ClassicSide(False), _ClassicSide(True)
    now = 0
    for step in steps:
        now += 100
        passes: list[list[can.Message]] = [[]]
        if step[0] == "grant":
            for side in (ref, c):
                side.service.request_grant(step[1], step[2] * 1_000_000, lambda reply: None)
        elif step[0] == "answer":
            _, node, kind, offset, how = step
            tx = max(0, (ref.service.core.session(node).tx if node != 7 else 1) + offset)
            msg = kind(node, tx & 0xFFFF)
            data, mac = classic(msg, tx | (0x1_0000 if how == "high" else 0), flip=how == "flip")
            other = Committed if kind is Ack else Ack
            passes = {
                "mac-less": [[data]],
                "lone-mac": [[mac]],
                "replaced": [[classic(other(node, tx & 0xFFFF), tx)[0], data, mac]],
                "cut": [[data, can.Message(arbitration_id=mac.arbitration_id, data=mac.data[:7])]],
                "split": [[data], [mac]],
            }.get(how, [[data, mac]])
        elif step[0] == "wait":
            now += step[1]
        else:
            for side in (ref, c):
                side.service.stop(now)
        for frames in passes:
            for side in (ref, c):
                side.wire.inbox.extend(copy.copy(f) for f in frames)
                side.step(now)
            assert c.seen() == ref.seen()
    ref.wire.shutdown()
    c.wire.shutdown()
    assert ref.service.frames_in_c == 0 and c.service.status()["frame_path"] == "c"
    event(f"answers taken in C: {min(c.service.frames_in_c, 3)}+")
