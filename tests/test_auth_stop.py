"""Authenticated mode and ``--on-intrusion stop``: what anyone on the bus can send (frames without
a MAC, with a bad one, replays) is refused, counted per node and reason with a rate and never
stops the supervisor; only authentic evidence does (a frame verified under a node's key in the
supervisor's own direction, with a freshness value it never used: a second supervisor holding the
master key). A replayed genuine frame of an earlier transaction is refused as stale, on both
sides."""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.auth.frames import (
    MAC_TYPE,
    AuthFailure,
    FrameAuth,
    Layout,
    Verdict,
    expected_freshness,
    freshness,
)
from canergy.auth.keys import derive_node_key, load_key
from canergy.cli import main
from canergy.codec import Codec
from canergy.core import Supervisor
from canergy.live.runtime import (
    OWN_MAC_WAIT_US,
    BusCounters,
    BusRuntime,
    OwnDirection,
    monotonic_us,
)
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.control import request as ask
from canergy.live.supervisor.service import JOIN_HOLD_US, ServiceConfig, SupervisorService
from canergy.messages import (
    Ack,
    Admit,
    Commit,
    Committed,
    Direction,
    Intention,
    Join,
    Message,
    MsgType,
    Return,
    ReturnAck,
    Telemetry,
)
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

CODEC = Codec()
KEY = bytes(range(16))
STALE = AuthFailure.STALE.value
NO_MAC = AuthFailure.UNAUTHENTICATED.value


def key(node: int) -> bytes:
    return derive_node_key(KEY, node, 1)


def side(layout: Layout, receives: Direction, tx: int, seq: int) -> FrameAuth:
    """An authenticator whose counters are ``tx`` and ``seq`` and that refuses older frames."""
    return FrameAuth(CODEC, layout, key, receives, lambda m: expected_freshness(m, tx, seq))


def sender(layout: Layout, direction: Direction, tx: int, seq: int) -> FrameAuth:
    """What builds the frames of ``direction`` with counters ``tx`` and ``seq``."""
    receives = Direction.TO_SUPERVISOR if direction is Direction.TO_CLIENT else Direction.TO_CLIENT
    return FrameAuth(CODEC, layout, key, receives, lambda m: freshness(m, tx, seq))


def last(auth: FrameAuth, frames: list[can.Message]) -> Any:
    return [auth.accept(f) for f in frames][-1]


# --- stale refusals, frame by frame ------------------------------------------------------------


@pytest.mark.parametrize("layout", list(Layout))
@pytest.mark.parametrize(
    "msg",
    [
        *(Ack(3, 7), Committed(3, 7), Return(3, 7, 20)),
        *(Intention(3, 7, 500, 0), Commit(3, 7, 500), ReturnAck(3, 7)),
    ],
)
def test_a_genuine_frame_older_than_the_receivers_counter_is_stale(
    layout: Layout, msg: Message
) -> None:
    """Sent at counter 7; received at 9 (an earlier transaction or return, replayed): stale,
    not MAC BAD. At 7 it is a current duplicate and passes; at 6 it is the next one."""
    receives = msg.TYPE.direction
    frames = sender(layout, receives, 7, 7).frames(msg)
    assert last(side(layout, receives, 9, 9), frames).failure is AuthFailure.STALE
    for counter in (7, 6):
        assert last(side(layout, receives, counter, counter), frames).message == msg
    tampered = [
        can.Message(arbitration_id=f.arbitration_id, data=bytearray(f.data), is_fd=f.is_fd)
        for f in frames
    ]
    tampered[-1].data[-1] ^= 1
    assert last(side(layout, receives, 9, 9), tampered).failure is AuthFailure.MAC_BAD


@pytest.mark.parametrize("layout", list(Layout))
def test_plain_freshness_keeps_checking_the_fv_alone(layout: Layout) -> None:
    """``freshness`` (a plain int, what the C client computes) still takes an older frame whose
    16-bit counter extends to its FV: only ``expected_freshness`` refuses it."""
    frames = sender(layout, Direction.TO_SUPERVISOR, 7, 0).frames(Committed(3, 7))
    plain = FrameAuth(CODEC, layout, key, Direction.TO_SUPERVISOR, lambda m: freshness(m, 9, 0))
    assert last(plain, frames).message == Committed(3, 7)


@pytest.mark.parametrize("layout", list(Layout))
@pytest.mark.parametrize("base", [0, 0xFFFF, 0x1_2345])
def test_telemetry_is_fresh_from_the_last_transaction_the_node_resolved(
    layout: Layout, base: int
) -> None:
    """A level only rises when the node resolves a transaction: a TELEMETRY from before the
    last one it is known to have resolved would report less than it holds (replayed, it drew
    top-ups: issue 30, item 6). Its FV is the node's last resolved transaction; classic frames
    carry its low half (``base`` crosses the half's wrap)."""

    def telemetry(resolved: int, level: int = 40) -> list[can.Message]:
        return sender(layout, Direction.TO_SUPERVISOR, base + resolved, 0).frames(
            Telemetry(3, level)
        )

    def verdict(auth: FrameAuth, resolved: int) -> Any:
        return last(auth, telemetry(resolved))

    supervisor = side(layout, Direction.TO_SUPERVISOR, base + 9, 0)
    # nothing known yet: the supervisor's transaction, or the one before it (not yet resolved)
    assert verdict(supervisor, 7).failure is AuthFailure.STALE
    assert verdict(supervisor, 10).failure is AuthFailure.STALE  # ahead of the supervisor
    assert verdict(supervisor, 8).message == Telemetry(3, 40)
    assert verdict(supervisor, 9).message == Telemetry(3, 40)
    assert verdict(supervisor, 8).failure is AuthFailure.STALE  # 9 was taken: 8 is past
    # a resolution seen in the node's answers moves the window too
    supervisor = side(layout, Direction.TO_SUPERVISOR, base + 9, 0)
    wire = (base + 9) & 0xFFFF
    answer = sender(layout, Direction.TO_SUPERVISOR, base + 9, 0).frames(Committed(3, wire))
    assert last(supervisor, answer).message is not None
    assert verdict(supervisor, 8).failure is AuthFailure.STALE
    supervisor = side(layout, Direction.TO_SUPERVISOR, base + 9, 0)
    ack = sender(layout, Direction.TO_SUPERVISOR, base + 9, 0).frames(Ack(3, wire))
    assert last(supervisor, ack).message is not None
    assert verdict(supervisor, 7).failure is AuthFailure.STALE
    assert verdict(supervisor, 8).message == Telemetry(3, 40)  # ACK 9: 8 resolved, 9 open
    # a forged or damaged one is still MAC BAD
    tampered = telemetry(9)
    tampered[-1] = can.Message(
        arbitration_id=tampered[-1].arbitration_id,
        data=bytes(tampered[-1].data[:-1]) + bytes([tampered[-1].data[-1] ^ 1]),
        is_fd=tampered[-1].is_fd,
    )
    assert last(supervisor, tampered).failure is AuthFailure.MAC_BAD


# --- frames in the supervisor's own direction ---------------------------------------------------


def own(layout: Layout, tx: int) -> tuple[OwnDirection, FrameAuth]:
    auth = side(layout, Direction.TO_SUPERVISOR, tx, 0)
    return OwnDirection(auth), auth


@pytest.mark.parametrize("layout", list(Layout))
def test_own_direction_frames_are_refused_unless_authentic_and_new(layout: Layout) -> None:
    checker, auth = own(layout, 10)
    # without a MAC: refused (classic: once its MAC frame has not followed in time)
    arbitration_id, data = CODEC.encode(Intention(3, 11, 500, 0))
    outcome = checker.check(can.Message(arbitration_id=arbitration_id, data=data), 0)
    if layout is Layout.CLASSIC:
        assert outcome is None and checker.expire(OWN_MAC_WAIT_US - 1) == []
        (outcome,) = checker.expire(OWN_MAC_WAIT_US)
    assert outcome is not None and outcome.refused is not None
    assert outcome.refused.failure is AuthFailure.UNAUTHENTICATED and outcome.refused.node == 3
    assert outcome.frame.arbitration_id == arbitration_id

    def verdict(msg: Message, tx: int) -> Any:
        frames = sender(layout, Direction.TO_CLIENT, tx, 0).frames(msg)
        outcomes = [checker.check(f, 0) for f in frames]
        assert outcomes[:-1] == [None] * (len(frames) - 1)
        return outcomes[-1]

    # verified, at or below the supervisor's counter: a replay of its own frames
    for tx in (10, 9):
        refused = verdict(Intention(3, tx, 500, 0), tx).refused
        assert refused is not None and refused.failure is AuthFailure.STALE
    # verified and newer than anything it sent: authentic evidence
    evidence = verdict(Commit(3, 12, 500), 12)
    assert evidence is not None and evidence.refused is None
    assert evidence.frame.arbitration_id == CODEC.encode(Commit(3, 12, 500))[0]
    # what the supervisor sends itself is its own from then on
    checker.note_sent(Intention(3, 12, 500, 0))
    refused = verdict(Intention(3, 12, 500, 0), 12).refused
    assert refused is not None and refused.failure is AuthFailure.STALE
    # a bad MAC in its direction: refused as MAC BAD
    frames = sender(layout, Direction.TO_CLIENT, 20, 0).frames(Commit(3, 20, 1))
    frames[-1] = can.Message(
        arbitration_id=frames[-1].arbitration_id,
        data=bytes(frames[-1].data[:-1]) + bytes([frames[-1].data[-1] ^ 1]),
        is_fd=frames[-1].is_fd,
    )
    outcomes = [checker.check(f, 0) for f in frames]
    assert outcomes[-1] is not None and outcomes[-1].refused is not None
    assert outcomes[-1].refused.failure is AuthFailure.MAC_BAD
    assert auth.pending == {}  # the receiving side's state is not touched


def test_without_a_key_stop_evidence_still_stops_and_with_one_only_authentic_evidence() -> None:
    def service() -> SupervisorService:
        core = Supervisor((1,), 10_000_000)
        return build_service(core, ServiceConfig(stop_on_intrusion=True, fsync=False), 0)

    plain = service()
    plain.intrusion(1, "f", "a frame only this supervisor sends", 0, stop=True)
    assert plain.stopping and plain.stopped_by_intrusion
    keyed = service()
    keyed.bus_counters.auth = "fd"
    assert keyed.authenticated
    keyed.intrusion(1, "f", "evidence anyone without a key can make", 0, stop=True)
    assert not keyed.stopping and keyed.intrusions.total == 1
    keyed.authentic_intrusion(1, "f", "a node's verified report", 0)
    assert keyed.stopping and keyed.stopped_by_intrusion
    assert keyed.status()["intrusion_report"]["authentic"] == {"total": 1, "by_node": {"1": 1}}


# --- the live stack on the virtual bus ----------------------------------------------------------


@dataclass
class Bench:
    tmp: Path
    layout: Layout
    rogue: can.BusABC
    sniffer: can.BusABC
    node: FirmwareNode
    node_runtime: BusRuntime
    result: list[int]
    thread: threading.Thread

    def status(self) -> dict[str, Any]:
        try:
            return dict(json.loads((self.tmp / "status.json").read_text()))
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def wait(self, condition: Callable[[], Any], timeout: float = 30) -> None:
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, "timed out"
            time.sleep(0.01)

    def committed(self) -> int:
        return int(self.status().get("nodes", {}).get("1", {}).get("committed", 0))

    def refused(self, reason: str) -> int:
        reasons = self.status().get("refused", {}).get("by_node", {}).get("1", {})
        return int(reasons.get("reasons", {}).get(reason, {}).get("count", 0))

    def plain(self, msg: Message) -> int:
        """``msg`` as anyone without the key sends it: the codec's frame, no MAC. When it
        left (monotonic µs)."""
        arbitration_id, data = CODEC.encode(msg)
        sent = monotonic_us()
        self.rogue.send(can.Message(arbitration_id=arbitration_id, data=data))
        return sent

    def send(self, frames: list[can.Message]) -> int:
        sent = monotonic_us()
        for frame in frames:
            self.rogue.send(frame)
        return sent


@pytest.fixture(params=list(Layout))
def bench(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Bench]:
    layout: Layout = request.param
    fd = layout is Layout.FD
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    channel = f"auth-stop-{uuid.uuid4().hex}"
    node = FirmwareNode(
        1,
        NvStore(tmp_path / "1.nv", 1, fsync=False),
        NodeConfig(return_above=600_000, telemetry_period_us=100_000),
        monotonic_us(),
    )
    host = NodeHost([node])
    node_key = load_key(tmp_path / "m.key").node_key(1)
    node_bus = can.Bus(
        interface="virtual", channel=channel, fd=fd, can_filters=CODEC.client_watch_filters(1)
    )
    auth = FrameAuth(CODEC, layout, lambda n: node_key, Direction.TO_CLIENT, host.freshness)
    runtime = BusRuntime(node_bus, host, codec=CODEC, receives=Direction.TO_CLIENT, auth=auth)
    loop = Loop(runtime)
    sniffer = can.Bus(interface="virtual", channel=channel, fd=fd)
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel, *(["--fd"] if fd else [])),
        *("--nodes", "1", "--initial", "10J", "--target", "1J", "--max-grant", "0.5J"),
        *("--auth", str(tmp_path / "m.key"), "--on-intrusion", "stop"),
        *("--state", str(tmp_path / "s.json"), "--no-fsync"),
        *("--status-file", str(tmp_path / "status.json"), "--status-period", "50ms"),
        # 2 s for an answer: at 100 ms a 0.5 s stall of the host timed a transaction out, and
        # the node's genuine answer to it came in stale (a refusal the flood test did not make)
        *("--control", str(tmp_path / "ctl.sock"), "--response-timeout", "2s"),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    rogue = can.Bus(interface="virtual", channel=channel, fd=fd)
    b = Bench(tmp_path, layout, rogue, sniffer, node, runtime, result, thread)
    try:
        b.wait(lambda: b.committed() >= 1)
        yield b
    finally:
        if thread.is_alive() and (tmp_path / "ctl.sock").exists():
            ask(tmp_path / "ctl.sock", {"stop": True}, 30)
        thread.join(timeout=60)
        loop.halt()
        rogue.shutdown()
        sniffer.shutdown()


def _latency_ms(b: Bench, reason: str, sent: int) -> float:
    events = [e for e in b.status()["refused"]["recent"] if e["reason"] == reason]
    return float(events[-1]["time_us"] - sent) / 1000


def test_frames_without_a_mac_are_counted_and_never_stop_the_supervisor(bench: Bench) -> None:
    b = bench
    own_reason = f"{NO_MAC} (in the supervisor's direction)"
    # one plain frame in the supervisor's own direction: before, exit 3 within a few ms
    sent = b.plain(Intention(1, 40_000, 65_535, 0))
    b.wait(lambda: b.refused(own_reason) >= 1)
    own_ms = _latency_ms(b, own_reason, sent)
    # and in the node's direction (classic: counted once the node's next message displaces it)
    sent = b.plain(Return(1, 1_000, 65_535))
    b.wait(lambda: b.refused(NO_MAC) >= 1)
    up_ms = _latency_ms(b, NO_MAC, sent)
    before = b.committed()
    b.wait(lambda: b.committed() >= before + 2)  # still granting
    final = b.status()
    assert b.thread.is_alive() and not final["stopping"] and not final["stopped_by_intrusion"]
    assert final["auth"] == b.layout.value
    assert final["auth_failures"].get(NO_MAC, 0) >= 2
    assert final["nodes"]["1"]["refused"] >= 2
    assert final["intrusion_report"]["authentic"]["total"] == 0
    print(f"\n{b.layout.value}: counted after {own_ms:.1f} ms (own direction), {up_ms:.1f} ms")
    ask(b.tmp / "ctl.sock", {"stop": True}, 30)
    b.thread.join(timeout=60)
    assert b.result == [0]


def test_a_flood_is_rated_and_logged_at_most_once_a_second(
    bench: Bench, caplog: pytest.LogCaptureFixture
) -> None:
    b = bench
    caplog.set_level(logging.WARNING, logger="canergy.live.supervisor.intrusions")
    start = time.monotonic()
    rates = []
    while time.monotonic() - start < 2.5:
        for _ in range(20):
            b.plain(Commit(1, 50_000, 1))
            b.plain(Ack(1, 50_000))  # in the node's direction, MAC-less
        time.sleep(0.02)
        rates.append(b.status().get("refused", {}).get("per_s", 0))
    b.wait(lambda: b.status()["refused"]["total"] >= 100)
    assert max(rates) >= 50, rates
    refused = b.status()["refused"]["by_node"]["1"]
    assert refused["per_s"] >= 0 and refused["total"] >= 100
    assert f"{NO_MAC} (in the supervisor's direction)" in refused["reasons"]
    assert set(refused["reasons"]) <= {  # a MAC-less ACK may displace the node's own (classic)
        NO_MAC,
        f"{NO_MAC} (in the supervisor's direction)",
        AuthFailure.NO_DATA.value,
        AuthFailure.MAC_BAD.value,
    }
    lines = [r for r in caplog.records if "refused" in r.getMessage()]
    assert 2 <= len(lines) <= 5, [r.getMessage() for r in lines]  # 2.5 s: one a second
    assert b.thread.is_alive() and not b.status()["stopping"]


def test_a_second_supervisor_with_the_master_key_stops_it_with_status_3(
    bench: Bench, capsys: pytest.CaptureFixture[str]
) -> None:
    b = bench
    b.wait(lambda: b.committed() >= 2)
    tx = 1_000 + b.committed()  # beyond anything this supervisor began
    master = load_key(b.tmp / "m.key")
    second = FrameAuth(
        CODEC, b.layout, master.node_key, Direction.TO_SUPERVISOR, lambda m: freshness(m, tx, 0)
    )
    sent = b.send(second.frames(Intention(1, tx & 0xFFFF, 100, 0)))
    b.thread.join(timeout=60)
    took_ms = (monotonic_us() - sent) / 1000
    assert b.result == [3]
    final = b.status()
    assert final["stopped_by_intrusion"]
    report = final["intrusion_report"]
    assert report["authentic"] == {"total": 1, "by_node": {"1": 1}}
    (event,) = [e for e in report["recent"] if e.get("authentic")]
    assert "second supervisor" in event["kind"]
    assert "stopped on intrusion" in capsys.readouterr().err
    first_ms = (report["first_at_us"] - sent) / 1000
    with capsys.disabled():
        print(
            f"\n{b.layout.value}: second supervisor: seen after {first_ms:.1f} ms, "
            f"exit 3 after {took_ms:.0f} ms"
        )


def _genuine(
    b: Bench, captured: list[can.Message], msg_type: MsgType, tx: int
) -> list[can.Message]:
    """The frames of the genuine message ``msg_type`` of transaction ``tx`` in a capture (the
    classic layout: its data frame and the MAC frame after it)."""
    ident = CODEC.id_base | msg_type << 8 | 1
    mac_id = CODEC.id_base | MAC_TYPE[msg_type.direction] << 8 | 1
    for i, frame in enumerate(captured):
        if frame.arbitration_id != ident:
            continue
        if b.layout is Layout.FD:
            if int.from_bytes(frame.data[-12:-8], "big") == tx:
                return [frame]
            continue
        if getattr(CODEC.decode(ident, bytes(frame.data)), "tx", None) != tx:
            continue
        trailer = next(
            f for f in captured[i + 1 :] if f.arbitration_id == mac_id and f.data[0] == msg_type
        )
        return [frame, trailer]
    raise AssertionError(f"no {msg_type.name} of tx {tx} captured")


def test_a_replayed_frame_of_an_earlier_transaction_is_counted_as_stale(bench: Bench) -> None:
    b = bench
    b.wait(lambda: b.committed() >= 3)
    captured: list[can.Message] = []
    while (frame := b.sniffer.recv(0)) is not None:
        captured.append(frame)
    committed = _genuine(b, captured, MsgType.COMMITTED, 1)  # the node's, to the supervisor
    intention = _genuine(b, captured, MsgType.INTENTION, 1)  # the supervisor's own, to the node
    node_stale = b.node_runtime.counters.auth_failures.get(STALE, 0)
    sent = _replay(b, committed, lambda: b.refused(STALE) >= 1)
    up_ms = _latency_ms(b, STALE, sent)
    own_reason = f"{STALE} (in the supervisor's direction)"
    # a replay of its own frame: stale, not a second supervisor; the node refuses it as stale
    _replay(b, intention, lambda: b.refused(own_reason) >= 1)
    b.wait(lambda: b.node_runtime.counters.auth_failures.get(STALE, 0) >= node_stale + 1)
    before = b.committed()
    b.wait(lambda: b.committed() >= before + 1)
    final = b.status()
    assert final["auth_failures"][STALE] >= 2
    assert not final["stopping"] and final["intrusion_report"]["authentic"]["total"] == 0
    print(f"\n{b.layout.value}: replayed COMMITTED counted as stale after {up_ms:.1f} ms")


def _replay(b: Bench, frames: list[can.Message], counted: Callable[[], bool]) -> int:
    """Send ``frames`` again until ``counted`` (classic: a genuine frame of the node may land
    between a replayed message and its MAC frame, as it may between any two)."""
    for _ in range(5):
        sent = b.send(frames)
        end = time.monotonic() + 1
        while time.monotonic() < end:
            if counted():
                return sent
            time.sleep(0.01)
    raise AssertionError("the replay was never counted")


def _first_telemetry(b: Bench, captured: list[can.Message], joining: bool) -> list[can.Message]:
    """The node's first TELEMETRY in a capture sent without books (``joining``: bound to its
    JOIN) or with them, and in the classic layout the MAC frame after it."""
    ident = CODEC.id_base | MsgType.TELEMETRY << 8 | 1
    mac_id = CODEC.id_base | MAC_TYPE[Direction.TO_SUPERVISOR] << 8 | 1
    i = next(
        i
        for i, f in enumerate(captured)
        if f.arbitration_id == ident and bool(f.data[4] & Telemetry.JOINING) == joining
    )
    if b.layout is Layout.FD:
        return [captured[i]]
    trailer = next(
        f
        for f in captured[i + 1 :]
        if f.arbitration_id == mac_id and f.data[0] == MsgType.TELEMETRY
    )
    return [captured[i], trailer]


def test_a_replayed_telemetry_is_stale_and_moves_nothing(bench: Bench) -> None:
    """Issue 30, item 6: the node's genuine TELEMETRY at level 0, replayed every 50 ms for 3 s,
    drew the whole budget into the node. Now each is refused as stale (one sent without books
    and one sent with them, before its first grants), and the node holds what the policy gives
    it: 1 J target, 0.5 J grants."""
    b = bench
    b.wait(lambda: b.committed() >= 3)
    captured: list[can.Message] = []
    while (frame := b.sniffer.recv(0)) is not None:
        captured.append(frame)
    replayed = [_first_telemetry(b, captured, joining) for joining in (True, False)]
    levels = [CODEC.decode(r[0].arbitration_id, bytes(r[0].data[:8])) for r in replayed]
    assert all(isinstance(t, Telemetry) and t.level_mj < 500 for t in levels), levels
    before, highest = b.refused(STALE), 0
    end = time.monotonic() + 3
    while time.monotonic() < end:
        for frames in replayed:
            b.send(frames)
        highest = max(highest, b.node.client.state.usable)
        time.sleep(0.05)
    # counted as stale (classic: a genuine frame landing between a replayed message and its MAC
    # frame counts the pair as frames without a MAC instead, as any two frames may)
    b.wait(lambda: b.refused(STALE) >= before + 20)
    assert highest <= 1_500_000, highest  # target + one grant: the replays added nothing
    final = b.status()
    assert not final["stopping"] and final["intrusion_report"]["authentic"]["total"] == 0
    assert final["nodes"]["1"]["admitted"] == 1  # the JOIN's report did not admit it again
    delivered = final["nodes"]["1"]["delivered_uj"] - final["nodes"]["1"]["returns_credited_uj"]
    assert delivered <= 1_500_000, delivered


def test_a_replayed_join_neither_admits_nor_writes_off(bench: Bench) -> None:
    """Issue 30, item 7: replayed JOINs re-admitted a node 16-26 times a run, each writing off
    what was open. A verified JOIN now waits for the node's next TELEMETRY: one with its books
    shows it a replay, refused as stale within a telemetry period (100 ms here)."""
    b = bench
    b.wait(lambda: b.committed() >= 3)
    captured: list[can.Message] = []
    while (frame := b.sniffer.recv(0)) is not None:
        captured.append(frame)
    ident = CODEC.id_base | MsgType.JOIN << 8 | 1
    i = next(i for i, f in enumerate(captured) if f.arbitration_id == ident)
    join = captured[i : i + 1] if b.layout is Layout.FD else [captured[i], captured[i + 1]]
    reason = f"{STALE} (a JOIN of an earlier life: the node has its books)"
    for n in range(1, 6):
        sent = b.send(join)
        b.wait(lambda n=n: b.refused(reason) >= n, timeout=10)
        took_ms = _latency_ms(b, reason, sent)
        assert took_ms < 1000, took_ms
    before = b.committed()
    b.wait(lambda: b.committed() >= before + 1)  # and it goes on being granted
    node = b.status()["nodes"]["1"]
    assert node["admitted"] == 1 and node["written_off"] == 0, node


class AuthWire:
    """An authenticated supervisor and an emulated node, each behind its own ``BusRuntime`` on
    python-can's virtual bus, driven in one thread on an explicit clock: frames wait in the
    receiver's queue until that side is polled. ``tap`` records every frame; ``rogue`` sends."""

    def __init__(self, tmp: Path, layout: Layout) -> None:
        self.now = 0
        self.layout = layout
        channel = f"auth-wire-{uuid.uuid4().hex}"
        fd = layout is Layout.FD

        def bus() -> can.BusABC:
            return can.Bus(interface="virtual", channel=channel, fd=fd)

        config = ServiceConfig(fsync=False, status_period_us=10**12)
        counters = BusCounters()
        core = Supervisor((1,), 10_000_000)
        self.service = build_service(core, config, 0, bus_counters=counters)
        sup_auth = FrameAuth(CODEC, layout, key, Direction.TO_SUPERVISOR, self.service.freshness)
        self.sup = BusRuntime(
            bus(),
            self.service,
            receives=Direction.TO_SUPERVISOR,
            auth=sup_auth,
            clock=self.clock,
            counters=counters,
        )
        nv = NvStore(tmp / "1.nv", 1, fsync=False)
        self.node = FirmwareNode(1, nv, NodeConfig(telemetry_period_us=60_000_000), 0)
        host = NodeHost([self.node])
        node_auth = FrameAuth(CODEC, layout, key, Direction.TO_CLIENT, host.freshness)
        node_auth.join_fv[1] = 0xBEEF << 16 | self.node.client.state.nonce  # as firmware_model
        self.node_rt = BusRuntime(
            bus(), host, receives=Direction.TO_CLIENT, auth=node_auth, clock=self.clock
        )
        self.tap, self.rogue = bus(), bus()
        self.node_on = True

    def clock(self) -> int:
        return self.now

    def settle(self, now: int, *, supervisor_only: bool = False) -> None:
        """Poll both sides (or the supervisor alone; a node that is off is never polled) at
        ``now`` until no side sends anything more."""
        self.now = now
        sides = [self.sup] if supervisor_only or not self.node_on else [self.sup, self.node_rt]
        for _ in range(100):
            sent = sum(rt.counters.frames_sent for rt in sides)
            for rt in sides:
                rt.poll(0)
            if sum(rt.counters.frames_sent for rt in sides) == sent:
                return
        raise AssertionError("the two sides never went quiet")

    def recorded(self, ident: int, count: int = 1) -> list[can.Message]:
        """The first frame recorded on ``ident`` (and in the classic layout its MAC frame)."""
        frames = []
        while (f := self.tap.recv(0)) is not None:
            frames.append(f)
        i = next(i for i, f in enumerate(frames) if f.arbitration_id == ident)
        return frames[i : i + count]

    def node_status(self) -> dict[str, Any]:
        return dict(self.service.status()["nodes"]["1"])

    def close(self) -> None:
        for bus in (self.sup.bus, self.node_rt.bus, self.tap, self.rogue):
            bus.shutdown()


@pytest.fixture
def auth_wire(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[AuthWire]:
    wire = AuthWire(tmp_path, request.param)
    try:
        yield wire
    finally:
        wire.close()


def _join_and_its_telemetry(w: AuthWire) -> list[can.Message]:
    """The node's JOIN and its TELEMETRY without books as it sent them at its start."""
    per = 1 if w.layout is Layout.FD else 2
    return w.recorded(CODEC.id_base | MsgType.JOIN << 8 | 1, 2 * per)  # sent together


@pytest.mark.parametrize("auth_wire", list(Layout), indirect=True)
def test_a_join_replayed_with_its_telemetry_while_the_node_is_on_writes_nothing_off(
    auth_wire: AuthWire,
) -> None:
    """Issue 40, item 10: the node's JOIN and its TELEMETRY without books (bound to that JOIN),
    recorded at its start and replayed together while a transaction was in flight, admitted the
    node again and wrote the transaction off. Now the admission waits 500 ms after the
    TELEMETRY; the node, which is on, sees both frames in its name and reports at once with its
    books (its periodic report is a minute away), which refuses the JOIN as a replay at once.
    (With a transaction in flight the node's report of its commit would do too; idle, only its
    report of the frames in its name does.)"""
    w = auth_wire
    w.settle(0)
    replay = _join_and_its_telemetry(w)
    assert w.node.joining
    w.settle(JOIN_HOLD_US)  # no objection in the hold: admitted
    assert not w.node.joining and w.node_status()["admitted"] == 1
    replies: list[dict[str, Any]] = []
    t = 1_000_000
    for n in range(1, 4):
        w.service.request_grant(1, 500_000, replies.append)
        w.settle(t, supervisor_only=True)  # its INTENTION waits in the node's queue
        assert w.service.core.session(1).reserved == 500_000
        for frame in replay:
            w.rogue.send(frame)
        w.settle(t)
        reason = f"{STALE} (a JOIN of an earlier life: the node has its books)"
        assert w.service.refusals.by_node[1][reason].count == n
        assert w.service.refusals.recent[-1]["time_us"] == t  # on the frame, not a period on
        w.settle(t + 10 * JOIN_HOLD_US)
        t += 20 * JOIN_HOLD_US
    assert [r["outcome"] for r in replies] == ["COMMITTED"] * 3
    for frame in replay:  # and with nothing in flight, the node has nothing else to report
        w.rogue.send(frame)
    w.settle(t)
    w.settle(t + 10 * JOIN_HOLD_US)
    status = w.node_status()
    assert status["admitted"] == 1 and status["written_off"] == 0, status
    assert w.service.refusals.by_node[1][reason].count == 4
    assert w.node.client.state.usable == 1_500_000


@pytest.mark.parametrize("auth_wire", list(Layout), indirect=True)
def test_a_join_replayed_with_its_telemetry_while_the_node_is_off_is_the_residual(
    auth_wire: AuthWire,
) -> None:
    """What is left (docs/security.md): while the node is off nobody can object, so the replay
    is admitted 500 ms later and what was open is written off: booked as delivered, lost to the
    supervisor, never created. Further replays write off nothing more: nothing is open."""
    w = auth_wire
    w.settle(0)
    replay = _join_and_its_telemetry(w)
    w.settle(JOIN_HOLD_US)
    replies: list[dict[str, Any]] = []
    w.service.request_grant(1, 500_000, replies.append)
    w.settle(1_000_000, supervisor_only=True)
    w.node_on = False  # off, its INTENTION unheard
    for frame in replay:
        w.rogue.send(frame)
    w.settle(1_000_000)
    w.settle(1_000_000 + JOIN_HOLD_US - 1)
    assert w.node_status()["written_off"] == 0
    w.settle(1_000_000 + JOIN_HOLD_US)
    status = w.node_status()
    assert status["admitted"] == 2 and status["written_off"] == 1
    assert replies[0]["outcome"] == "WRITTEN_OFF"
    assert w.service.core.session(1).delivered == 500_000  # booked as delivered: lost
    for frame in replay:  # again and again: nothing more is open, nothing more written off
        w.rogue.send(frame)
    w.settle(2_000_000)
    w.settle(2_000_000 + JOIN_HOLD_US)
    assert w.node_status()["written_off"] == 1 and w.service.core.usable == 9_500_000


def test_a_node_reports_at_once_a_refused_frame_in_its_name(tmp_path: Path) -> None:
    """With a key, a frame in the node's own direction that fails the check (a replay of its
    own, no MAC, a bad one) is counted in its witness and reported at once, as the C node
    does (auth.c) and as without a key: the supervisor hears of a replayed JOIN before it
    could admit it."""
    node = FirmwareNode(1, NvStore(tmp_path / "1.nv", 1, fsync=False), NodeConfig(), 0)
    host = NodeHost([node])
    node.on_wakeup(0)
    frame = can.Message(arbitration_id=CODEC.id_base | MsgType.JOIN << 8 | 1, data=b"\0\0\0")
    host.on_auth_failure(Verdict(failure=AuthFailure.STALE, node=1), frame, 300_000)
    assert node.witnessed == 1 and node.next_wakeup() <= 300_000
    (report,) = [m for m in node.on_wakeup(300_000) if isinstance(m, Telemetry)]
    assert report.witness == 1
    to_node = can.Message(arbitration_id=CODEC.id_base | MsgType.ADMIT << 8 | 1, data=b"\0")
    host.on_auth_failure(Verdict(failure=AuthFailure.MAC_BAD, node=1), to_node, 400_000)
    assert node.witnessed == 1  # the supervisor's direction: not in its name


def test_a_gateway_reports_at_once_a_refused_frame_in_its_name_above() -> None:
    """The gateway's upstream leg is a node to the supervisor above: the same rule."""
    from canergy.core.gateway import Gateway
    from canergy.live.gateway.process import GatewayFiles, Uplink, UplinkConfig

    gateway = Gateway(5, (1, 2))
    up = Uplink(
        gateway, UplinkConfig(telemetry_period_us=60_000_000), GatewayFiles(gateway, None), 0
    )
    up.on_wakeup(0)
    assert up.next_wakeup() == 50_000  # its tick; its TELEMETRY a minute away
    frame = can.Message(arbitration_id=CODEC.id_base | MsgType.JOIN << 8 | 5, data=b"\0\0\0")
    up.on_auth_failure(Verdict(failure=AuthFailure.STALE, node=5), frame, 10_000)
    assert up.witnessing.count == 1 and up.next_wakeup() == 10_000
    (report,) = [m for m in up.on_wakeup(10_000) if isinstance(m, Telemetry)]
    assert report.witness == 1


def test_a_join_resent_while_its_admit_was_on_the_way_is_no_replay() -> None:
    """Found in CI: the node re-sent its JOIN (same nonce, same FV: the same bytes) before the
    slow ADMIT reached it; the supervisor held the copy until the node's next TELEMETRY, which
    showed books, and counted the node's own re-send as a replayed JOIN. A copy of the JOIN
    admitted last, decided by the first TELEMETRY with books after it, is dropped; a later copy
    is the replay it was before; a copy the node follows with a TELEMETRY still JOINING (its
    ADMIT was lost) is admitted again."""
    core = Supervisor((1,), 10_000_000)
    config = ServiceConfig(fsync=False, status_period_us=10**12, join_hold_us=0)  # no hold here
    service = build_service(core, config, 0, bus_counters=BusCounters(auth=Layout.FD.value))
    joining, books = Telemetry(1, 0, flags=Telemetry.JOINING), Telemetry(1, 0)

    def node_status() -> Any:
        return service.status()["nodes"]["1"]

    assert not service.on_message(Join(1, 7), 1_000)  # held until the node's report
    assert [m for m in service.on_message(joining, 2_000) if isinstance(m, Admit)]
    assert not service.on_message(Join(1, 7), 3_000)  # its re-send, the ADMIT on the way
    service.on_message(books, 4_000)
    assert service.intrusions.total == 0 and service.refusals.of_node(1) == 0
    assert node_status()["admitted"] == 1 and node_status()["joins_resent"] == 1

    service.on_message(Join(1, 7), 5_000)  # the same bytes once the node showed its books
    service.on_message(books, 6_000)
    assert service.intrusions.total == 1 and node_status()["admitted"] == 1

    service.on_message(Join(1, 9), 6_100)  # a new life: admitted...
    assert [m for m in service.on_message(joining, 6_200) if isinstance(m, Admit)]
    service.on_message(Join(1, 5), 6_300)  # ...an earlier life's JOIN replayed, then the
    service.on_message(Join(1, 9), 6_400)  # node's own re-send of the JOIN just admitted
    service.on_message(books, 6_500)  # each judged: the earlier life's is still reported
    assert service.intrusions.total == 2 and node_status()["joins_resent"] == 2
    assert node_status()["admitted"] == 2

    for nonce in range(100, 110):  # ten replays of earlier lives: the latest 8 are judged
        service.on_message(Join(1, nonce), 6_600)
    service.on_message(books, 6_700)
    assert service.intrusions.total == 10 and node_status()["admitted"] == 2

    service.on_message(Join(1, 11), 7_000)  # another life, whose ADMIT is lost
    assert [m for m in service.on_message(joining, 8_000) if isinstance(m, Admit)]
    service.on_message(Join(1, 11), 9_000)
    assert [m for m in service.on_message(joining, 10_000) if isinstance(m, Admit)]
    service.on_message(books, 11_000)
    assert node_status()["admitted"] == 4 and node_status()["joins_resent"] == 2
    assert service.intrusions.total == 10


pytestmark = pytest.mark.usefixtures("both_cores")
"""Each test on the Python core and on the compiled one (tests/conftest.py)."""
