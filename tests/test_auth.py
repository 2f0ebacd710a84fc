"""Authenticated mode: key files, the two frame layouts, and on the virtual bus every forgery of
the security issue and replays of a capture move nothing and are counted."""

from __future__ import annotations

import json
import os
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.auth.frames import (
    FV_MASK,
    AuthFailure,
    FrameAuth,
    Layout,
    expected_freshness,
    freshness,
)
from canergy.auth.keys import KeyFileError, derive_node_key, load_key, new_master, write_key
from canergy.cli import main
from canergy.codec import Codec
from canergy.core.actions import Send
from canergy.core.state import Session, SupervisorState
from canergy.core.supervisor import Supervisor
from canergy.ledger import ledger_from_status
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.messages import (
    Ack,
    Admit,
    Commit,
    Committed,
    Direction,
    Intention,
    Join,
    Message,
    Return,
    ReturnAck,
    Telemetry,
)
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

CODEC = Codec()
KEY = bytes(range(16))


def pair(layout: Layout, tx: int = 0, seq: int = 0) -> tuple[FrameAuth, FrameAuth]:
    """A supervisor's and a node's authenticator, both at counters ``tx`` and ``seq``."""

    def fresh(msg: Message) -> int:
        return freshness(msg, tx, seq)

    def key(node: int) -> bytes:
        return derive_node_key(KEY, node, 1)

    sup = FrameAuth(CODEC, layout, key, Direction.TO_SUPERVISOR, fresh)
    node = FrameAuth(CODEC, layout, key, Direction.TO_CLIENT, fresh)
    return sup, node


def deliver(receiver: FrameAuth, frames: list[can.Message]) -> list[Any]:
    return [receiver.accept(f) for f in frames]


MESSAGES_DOWN = [Intention(3, 1, 500, 0), Commit(3, 1, 500), ReturnAck(3, 1), Admit(3, 7, 1, 0)]
MESSAGES_UP = [Ack(3, 1), Committed(3, 1), Return(3, 1, 20), Join(3, 7), Telemetry(3, 40)]


@pytest.mark.parametrize("layout", list(Layout))
def test_every_message_round_trips_and_a_changed_bit_does_not(layout: Layout) -> None:
    sup, node = pair(layout, tx=1, seq=1)
    for sender, receiver, messages in ((sup, node, MESSAGES_DOWN), (node, sup, MESSAGES_UP)):
        for msg in messages:
            frames = sender.frames(msg)
            assert len(frames) == (1 if layout is Layout.FD else 2)
            assert all(len(f.data) <= (64 if layout is Layout.FD else 8) for f in frames)
            assert deliver(receiver, frames)[-1].message == msg
            tampered = [
                can.Message(arbitration_id=f.arbitration_id, data=bytearray(f.data), is_fd=f.is_fd)
                for f in frames
            ]
            tampered[-1].data[-1] ^= 0x01  # the MAC's last byte
            assert deliver(receiver, tampered)[-1].failure is AuthFailure.MAC_BAD


@pytest.mark.parametrize("layout", list(Layout))
def test_a_frame_built_without_the_key_is_refused(layout: Layout) -> None:
    _, node = pair(layout)
    arbitration_id, data = CODEC.encode(Commit(3, 1, 65535))  # the public codec, no key
    plain = can.Message(arbitration_id=arbitration_id, data=data)
    verdict = node.accept(plain)
    assert verdict.message is None  # FD: no MAC at all; classic: waits for a MAC never coming
    if layout is Layout.FD:
        assert verdict.failure is AuthFailure.UNAUTHENTICATED
    else:
        guess = can.Message(
            arbitration_id=CODEC.id_base | 3, data=bytes([0x2, 0, 0, 1, 2, 3, 4, 5])
        )
        assert node.accept(guess).failure is AuthFailure.MAC_BAD


@pytest.mark.parametrize("layout", list(Layout))
def test_a_replay_from_65536_transactions_ago_is_stale(layout: Layout) -> None:
    old_sup, _ = pair(layout, tx=5)
    _, node = pair(layout, tx=5 + 65536)
    frames = old_sup.frames(Intention(3, 6, 500, 0))  # same 16-bit tx on the wire, another FV
    assert deliver(node, frames)[-1].failure is AuthFailure.STALE


def test_kdf_gives_each_node_and_epoch_its_own_key() -> None:
    keys = {derive_node_key(KEY, n, e) for n in (1, 2) for e in (1, 2)}
    assert len(keys) == 4


def test_key_files_are_0600_and_never_show_the_key(tmp_path: Path) -> None:
    path = tmp_path / "m.key"
    key = new_master(3)
    write_key(path, key)
    assert os.stat(path).st_mode & 0o777 == 0o600
    assert load_key(path) == key and key.secret.hex() not in repr(key)
    os.chmod(path, 0o644)
    with pytest.raises(KeyFileError, match="chmod 600") as refused:
        load_key(path)
    assert key.secret.hex() not in str(refused.value)
    os.chmod(path, 0o600)
    path.write_text(path.read_text().replace("kind=master", "kind=other"))
    with pytest.raises(KeyFileError, match="kind"):
        load_key(path)
    with pytest.raises(KeyFileError, match="never replaced"):
        write_key(path, key)


def test_a_node_key_serves_only_its_node(tmp_path: Path) -> None:
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    assert (
        main(
            [
                "keys",
                "--master",
                str(tmp_path / "m.key"),
                "--nodes",
                "2",
                "-o",
                str(tmp_path / "n2.key"),
            ]
        )
        == 0
    )
    node_key = load_key(tmp_path / "n2.key")
    assert node_key.node_key(2) == load_key(tmp_path / "m.key").node_key(2)
    with pytest.raises(KeyFileError, match="cannot serve node 3"):
        node_key.node_key(3)


def test_node_keys_take_their_masters_epoch_and_another_epoch_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--epoch belongs to a master key: with --master, an epoch other than the master's is
    refused (keys of it would verify with no supervisor), its own is accepted."""
    master = tmp_path / "m.key"
    assert main(["keys", "-o", str(master), "--epoch", "2"]) == 0
    derive = ["keys", "--master", str(master), "--nodes", "1", "-o"]
    assert main([*derive, str(tmp_path / "d3"), "--epoch", "3"]) == 2
    assert "--epoch 3: node keys take the epoch of their master key" in capsys.readouterr().err
    assert not (tmp_path / "d3").exists()
    assert main([*derive, str(tmp_path / "d2"), "--epoch", "2"]) == 0
    assert main([*derive, str(tmp_path / "d")]) == 0
    for folder in ("d2", "d"):
        key = load_key(tmp_path / folder / "node-001.key")
        assert key.epoch == 2
        assert key.secret == derive_node_key(load_key(master).secret, 1, 2)


# --- the live stack on the virtual bus ---------------------------------------------------------


@dataclass
class Bench:
    tmp: Path
    layout: Layout
    rogue: can.BusABC
    sniffer: can.BusABC
    host: NodeHost
    result: list[int]
    thread: threading.Thread

    def status(self) -> dict[str, Any]:
        try:
            return dict(json.loads((self.tmp / "status.json").read_text()))
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def wait(self, condition: Any, timeout: float = 30) -> None:
        end = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < end, "timed out"
            time.sleep(0.02)

    def send(self, frame: can.Message) -> None:
        self.rogue.send(frame)

    def forge(self, msg: Message) -> None:
        """What a participant without the key can build: the codec's frame, in this layout's
        shape with a MAC of zeros."""
        arbitration_id, data = CODEC.encode(msg)
        if self.layout is Layout.FD:
            length = 16 if len(data) <= 4 else 20
            self.send(
                can.Message(
                    arbitration_id=arbitration_id, is_fd=True, data=data + bytes(length - len(data))
                )
            )
        else:
            self.send(can.Message(arbitration_id=arbitration_id, data=data))
            kind = 0x0 if msg.TYPE < 8 else 0x8
            trailer = bytes([msg.TYPE]) + bytes(7)
            self.send(
                can.Message(arbitration_id=CODEC.id_base | kind << 8 | msg.node, data=trailer)
            )


@pytest.fixture(params=list(Layout))
def bench(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Bench]:
    layout: Layout = request.param
    fd = layout is Layout.FD
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    assert (
        main(
            [
                "keys",
                "--master",
                str(tmp_path / "m.key"),
                "--nodes",
                "1",
                "-o",
                str(tmp_path / "n1.key"),
            ]
        )
        == 0
    )
    channel = f"auth-{uuid.uuid4().hex}"
    now = monotonic_us()
    node = FirmwareNode(
        1,
        NvStore(tmp_path / "1.nv", 1, fsync=False),
        NodeConfig(return_above=600_000, telemetry_period_us=100_000),
        now,
    )
    host = NodeHost([node])
    node_key = load_key(tmp_path / "n1.key").node_key(1)
    node_bus = can.Bus(
        interface="virtual", channel=channel, fd=fd, can_filters=CODEC.client_watch_filters(1)
    )
    auth = FrameAuth(CODEC, layout, lambda n: node_key, Direction.TO_CLIENT, host.freshness)
    loop = Loop(BusRuntime(node_bus, host, codec=CODEC, receives=Direction.TO_CLIENT, auth=auth))
    sniffer = can.Bus(interface="virtual", channel=channel, fd=fd)
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel, *(["--fd"] if fd else [])),
        *("--nodes", "1", "--initial", "10J", "--target", "1J", "--max-grant", "0.5J"),
        *("--auth", str(tmp_path / "m.key")),
        *("--state", str(tmp_path / "s.json"), "--no-fsync"),
        *("--status-file", str(tmp_path / "status.json"), "--status-period", "50ms"),
        *("--control", str(tmp_path / "ctl.sock"), "--response-timeout", "100ms"),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    rogue = can.Bus(interface="virtual", channel=channel, fd=fd)
    b = Bench(tmp_path, layout, rogue, sniffer, host, result, thread)
    try:
        yield b
    finally:
        if thread.is_alive() and (tmp_path / "ctl.sock").exists():
            request(tmp_path / "ctl.sock", {"stop": True}, 30)
        thread.join(timeout=60)
        loop.halt()
        rogue.shutdown()
        sniffer.shutdown()


def test_authenticated_traffic_flows_and_forgeries_move_nothing(bench: Bench) -> None:
    b = bench
    node = b.host.nodes[1]
    b.wait(lambda: b.status().get("nodes", {}).get("1", {}).get("committed", 0) >= 2)
    captured: list[can.Message] = []
    while (frame := b.sniffer.recv(0)) is not None:
        captured.append(frame)
    assert captured and all(f.is_fd == (b.layout is Layout.FD) for f in captured)
    session = b.status()["nodes"]["1"]
    tx, seq = session["open_tx"] or 0, session["returns_credited"]
    # every forgery of the security issue, built with the public codec and no key
    for forged in (
        Commit(1, tx + 1, 65535),
        Intention(1, tx + 1, 65535, 0),
        Intention(1, tx + 1, 1, 4_000_000),
        Intention(1, tx + 30_000, 1, 0),
        Return(1, seq + 1, 65535),
        ReturnAck(1, seq + 1),
        Return(1, seq + 1, 1),
    ):
        b.forge(forged)
    for frame in captured:  # and a replay of everything seen so far
        b.send(frame)
    b.wait(lambda: node.intrusions.total >= 4 and b.status().get("intrusions", 0) >= 2)
    time.sleep(0.5)
    assert sum(b.status()["auth_failures"].values()) >= 2
    request(b.tmp / "ctl.sock", {"stop": True}, 30)
    b.thread.join(timeout=60)
    assert b.result == [0]
    final = b.status()
    # a forged COMMIT or INTENTION crediting the node, or a forged RETURN crediting the
    # supervisor, would show as energy generated
    books = ledger_from_status(final, [node.status()])
    assert books.passive and books.dissipated >= 0, books
    assert node.client.state.credited <= final["nodes"]["1"]["delivered_uj"]


# --- captures: dump, decode and audit with --auth ---------------------------------------------


def _capture(tmp: Path, layout: Layout, key_path: Path) -> tuple[Path, list[can.Message]]:
    """Two honest transactions through both cores and authenticators, as a candump -l file."""
    from canergy.core import Client, Send, Supervisor, Timing
    from canergy.live.supervisor.build import build_service
    from canergy.live.supervisor.service import ServiceConfig

    master = load_key(key_path)
    timing = Timing(response_timeout_us=10_000, retries=3)
    service = build_service(
        Supervisor((1,), 10_000_000, timing=timing),
        ServiceConfig(fsync=False, status_period_us=10**12),
        0,
    )
    client = Client(1, timing=timing)
    sup_auth = FrameAuth(CODEC, layout, master.node_key, Direction.TO_SUPERVISOR, service.freshness)
    node_auth = FrameAuth(
        CODEC,
        layout,
        master.node_key,
        Direction.TO_CLIENT,
        lambda m: freshness(m, client.state.last_tx, client.state.return_seq),
    )
    frames: list[can.Message] = []

    def carry(msgs: list[Message]) -> None:
        queue = list(msgs)
        while queue:
            msg = queue.pop(0)
            down = msg.TYPE.direction is Direction.TO_CLIENT
            sent = (sup_auth if down else node_auth).frames(msg)
            frames.extend(sent)
            verdicts = [(node_auth if down else sup_auth).accept(f) for f in sent]
            got = verdicts[-1].message
            assert got == msg
            if down:
                queue += [a.message for a in client.receive(got, 0) if isinstance(a, Send)]
            else:
                queue += list(service.on_message(got, 0))

    carry([Telemetry(1, 0)])
    for amount in (500_000, 250_000):
        answers: list[dict[str, Any]] = []
        service.request_grant(1, amount, answers.append)
        carry(list(service.on_wakeup(0)))
        assert answers[0]["outcome"] == "COMMITTED"
    path = tmp / f"{layout.value}.log"
    with can.Logger(str(path)) as log:
        for i, frame in enumerate(frames):
            frame.timestamp, frame.channel = 1_700_000_000 + i / 1000, "vcan0"
            log.on_message_received(frame)
    return path, frames


@pytest.mark.parametrize("layout", list(Layout))
def test_decode_and_audit_check_macs_in_a_capture(
    tmp_path: Path, layout: Layout, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    path, frames = _capture(tmp_path, layout, tmp_path / "m.key")
    capsys.readouterr()
    assert main(["decode", str(path), "--auth", str(tmp_path / "m.key")]) == 0
    out = capsys.readouterr().out
    assert out.count("mac ok") == len(frames) // (1 if layout is Layout.FD else 2)
    assert "MAC BAD" not in out and "INTENTION" in out
    assert main(["decode", str(path)]) == 0  # no key: the messages, unverified
    assert "mac ?" in capsys.readouterr().out
    assert main(["audit", str(path), "--auth", str(tmp_path / "m.key")]) == 0
    assert "no violation seen" in capsys.readouterr().out
    # a forged COMMIT with a made-up MAC, then the audit: refused and not booked
    forged = frames[-1]
    arbitration_id, data = CODEC.encode(Commit(1, 3, 65535))
    if layout is Layout.FD:
        body = data + bytes(fd_frame_len(len(data)) - len(data))
        extra = [can.Message(arbitration_id=arbitration_id, data=body, is_fd=True)]
    else:
        extra = [
            can.Message(arbitration_id=arbitration_id, data=data),
            can.Message(arbitration_id=CODEC.id_base | 1, data=bytes([2]) + bytes(7)),
        ]
    with can.Logger(str(path.with_suffix(".forged.log"))) as log:
        for frame in [*frames, *extra]:
            frame.timestamp = forged.timestamp + 1
            frame.channel = "vcan0"
            log.on_message_received(frame)
    capsys.readouterr()
    assert (
        main(["decode", str(path.with_suffix(".forged.log")), "--auth", str(tmp_path / "m.key")])
        == 0
    )
    assert "MAC BAD" in capsys.readouterr().out
    assert (
        main(
            [
                "audit",
                str(path.with_suffix(".forged.log")),
                "--auth",
                str(tmp_path / "m.key"),
                "--json",
            ]
        )
        == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["nodes"]["1"]["granted_uj"] == 750_000  # the forged 65.535 J is not booked


def fd_frame_len(n: int) -> int:
    from canergy.auth.frames import fd_length

    return fd_length(n + 12)


def test_a_single_run_grant_to_an_authenticated_node(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`canergy grant --auth` (no running supervisor) speaks the node's authenticated frames;
    without the key the node never takes its intention."""
    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    channel = f"auth-grant-{uuid.uuid4().hex}"
    node = FirmwareNode(1, NvStore(tmp_path / "1.nv", 1, fsync=False), NodeConfig(), monotonic_us())
    host = NodeHost([node])
    key = load_key(tmp_path / "m.key").node_key(1)
    auth = FrameAuth(CODEC, Layout.CLASSIC, lambda n: key, Direction.TO_CLIENT, host.freshness)
    bus = can.Bus(interface="virtual", channel=channel, can_filters=CODEC.client_watch_filters(1))
    loop = Loop(BusRuntime(bus, host, codec=CODEC, receives=Direction.TO_CLIENT, auth=auth))
    grant = ["grant", "-i", "virtual", "-c", channel, "--node", "1", "--amount", "0.5J"]
    try:
        time.sleep(0.3)  # the node's JOIN and telemetry
        plain = [*grant, "--state", str(tmp_path / "plain.json"), "--timeout", "1.5s"]
        assert main(plain) == 1  # frames without a MAC: the node takes nothing
        assert node.client.state.usable == 0
        signed = [*grant, "--state", str(tmp_path / "s.json"), "--auth", str(tmp_path / "m.key")]
        assert main(signed) == 0, capsys.readouterr().out
        assert node.client.state.usable == 500_000
        assert node.intrusions.total >= 1  # the plain run's frames, refused and counted
    finally:
        loop.halt()


def test_a_node_that_lost_its_nv_past_transaction_65535_is_granted_again(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 30: admitted at the wire's 16-bit counters, a node whose books were lost past
    transaction 65,535 could take no grant in authenticated mode (its freshness never met the
    supervisor's). The ADMIT now carries the full counters."""
    from canergy.auth.state_key import state_seal
    from canergy.live.supervisor.state_file import save_state

    assert main(["keys", "-o", str(tmp_path / "m.key")]) == 0
    master = load_key(tmp_path / "m.key")
    books = SupervisorState(
        10_000_000, 10_000_000, 0, (Session(1, tx=70_000, returns_credited=70_003),)
    )
    save_state(tmp_path / "s.json", books, "hardened", fsync=False, seal=state_seal(master))
    channel = f"auth-admit-{uuid.uuid4().hex}"
    config = NodeConfig(telemetry_period_us=100_000)
    node = FirmwareNode(1, NvStore(tmp_path / "1.nv", 1, fsync=False), config, monotonic_us())
    host = NodeHost([node])
    key = master.node_key(1)
    auth = FrameAuth(CODEC, Layout.CLASSIC, lambda n: key, Direction.TO_CLIENT, host.freshness)
    auth.join_fv[1] = 0xBEEF << 16 | node.client.state.nonce
    bus = can.Bus(interface="virtual", channel=channel, can_filters=CODEC.client_watch_filters(1))
    loop = Loop(BusRuntime(bus, host, codec=CODEC, receives=Direction.TO_CLIENT, auth=auth))
    grant = ["grant", "-i", "virtual", "-c", channel, "--node", "1", "--amount", "0.5J"]
    grant += ["--state", str(tmp_path / "s.json"), "--auth", str(tmp_path / "m.key")]
    try:
        assert main([*grant, "--no-fsync"]) == 0, capsys.readouterr().out
        assert node.client.state.usable == 500_000
        assert node.client.state.last_tx == 70_001  # the full counters, not 70,001 - 65,536
        assert node.client.state.return_seq == 70_003
    finally:
        loop.halt()


@pytest.mark.parametrize("layout", list(Layout))
def test_join_and_admit_carry_32_bits_of_freshness(layout: Layout) -> None:
    """A node draws 16 random bits above its JOIN nonce; the supervisor binds the JOIN's FV in
    the ADMIT's MAC. An ADMIT recorded in an earlier life whose 16-bit nonce happens to match
    fails its MAC."""
    sup, node = pair(layout)
    node.join_fv[3] = 0xBEEF << 16 | 7
    join = node.frames(Join(3, 7))
    assert deliver(sup, join)[-1].message == Join(3, 7) and sup.join_fv[3] == 0xBEEF0007
    admit = sup.frames(Admit(3, 7, 1, 0))
    assert deliver(node, admit)[-1].message == Admit(3, 7, 1, 0)
    old_sup, _ = pair(layout)
    old_sup.join_fv[3] = 0x1234 << 16 | 7  # the earlier life's JOIN, same 16-bit nonce
    replayed = old_sup.frames(Admit(3, 7, 1, 0))
    assert deliver(node, replayed)[-1].failure is AuthFailure.MAC_BAD


@pytest.mark.parametrize("layout", list(Layout))
@pytest.mark.parametrize(
    ("tx", "seq"),
    [(0x2_0005, 0x2_0001), (0x1_FFFF, 0x3), (0x3FFE_0003, 7)],  # the last high half below 2**30
)
def test_admit_carries_the_full_counters(layout: Layout, tx: int, seq: int) -> None:
    """Issue 30: a node admitted past transaction 65,535 took only the wire's 16 bits, so its
    freshness never met the supervisor's again. The supervisor's core moves both counters up to
    one high half at admission (never back) and the ADMIT's FV carries it."""
    books = SupervisorState(10_000_000, 10_000_000, 0, (Session(3, tx=tx, returns_credited=seq),))
    core = Supervisor((3,), 10_000_000, state=books)
    admit = next(a.message for a in core.receive(Join(3, 7), 0) if isinstance(a, Send))
    s = core.session(3)
    assert s.tx >> 16 == s.returns_credited >> 16 == max(tx >> 16, seq >> 16)
    assert s.tx & 0xFFFF == tx & 0xFFFF and s.returns_credited & 0xFFFF == seq & 0xFFFF
    sup = FrameAuth(
        CODEC,
        layout,
        lambda n: KEY,
        Direction.TO_SUPERVISOR,
        lambda m: expected_freshness(m, s.tx, s.returns_credited),
    )
    node = FrameAuth(
        CODEC, layout, lambda n: KEY, Direction.TO_CLIENT, lambda m: freshness(m, 0, 0)
    )
    node.join_fv[3] = sup.join_fv[3] = 0xBEEF << 16 | 7
    taken = deliver(node, sup.frames(admit))[-1].message
    assert taken == Admit(3, 7, s.tx & FV_MASK, s.returns_credited & FV_MASK)


@pytest.mark.parametrize("layout", list(Layout))
def test_a_frame_for_a_node_this_side_does_not_handle_is_left_alone(layout: Layout) -> None:
    """A supervisor with nodes 1-3 sees node 4's authenticated frames (another supervisor's, or
    a grant run for one node): nothing happens, nothing crashes, nothing is counted."""
    _, node4 = pair(layout)

    def only_1_to_3(msg: Message) -> int | None:
        return freshness(msg, 0, 0) if msg.node <= 3 else None

    sup = FrameAuth(CODEC, layout, lambda n: KEY, Direction.TO_SUPERVISOR, only_1_to_3)
    for msg in (Join(4, 9), Return(4, 1, 5), Ack(4, 1)):
        verdict = deliver(sup, node4.frames(msg))[-1]
        assert verdict.message is None and verdict.failure is None


def test_a_capture_checked_with_a_node_key_leaves_other_nodes_unverified(tmp_path: Path) -> None:
    from canergy.auth.capture import CaptureAuth
    from canergy.auth.keys import Key

    sup, _ = pair(Layout.FD)
    own = Key("node", 1, derive_node_key(KEY, 3, 1), 3)
    capture = CaptureAuth(CODEC, own)
    mine, other = sup.frames(Intention(3, 1, 5, 0))[0], sup.frames(Intention(4, 1, 5, 0))[0]
    assert capture.describe(mine).mac == "ok"
    assert capture.describe(other).mac == "unverified"
