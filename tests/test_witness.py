"""The node as the witness for its own id (security second pass, items 1-4): without a key, a
forged RETURN is refuted by the node's own TELEMETRY and never credited; frames in a node's name
are reported by the node and raised by the supervisor within a second; a node whose TELEMETRY
contradicts itself gets no top-ups; returns acknowledged in the supervisor's name while it was
away resynchronise."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from support.harness import Harness
from support.intrusion_bench import Bench, bench

from canergy.cli import build_parser
from canergy.codec import Codec
from canergy.core import Supervisor
from canergy.live.runtime import monotonic_us
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.service import JOIN_HOLD_US, ServiceConfig
from canergy.live.supervisor.witness import (
    RETURN_HOLD_MIN_US,
    WITNESS_GAP_US,
    WITNESS_REPORT_AT,
    ReturnGate,
)
from canergy.messages import (
    Intention,
    Join,
    Message,
    Return,
    ReturnAck,
    Telemetry,
    ToClient,
)
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

HOLD = 300_000


def tel(return_seq: int, witness: int = 0, node: int = 1, level_mj: int = 0) -> Telemetry:
    return Telemetry(node, level_mj, 0, return_seq, witness)


def test_a_return_is_released_only_a_hold_after_the_node_confirmed_it() -> None:
    gate = ReturnGate(HOLD, 10_000_000)
    gate.telemetry(tel(0), 0, 0)
    assert gate.hold(Return(1, 1, 700), 0, 1_000) is None
    assert gate.release(1, 0, 1_000 + HOLD) == []  # the node has not said it made return 1
    gate.telemetry(tel(1), 0, 50_000)
    assert gate.release(1, 0, 50_000) == []  # confirmed just now: the node may still refute
    assert gate.release(1, 0, 49_999 + HOLD) == []
    assert gate.release(1, 0, 50_000 + HOLD) == [Return(1, 1, 700)]
    assert gate.release(1, 1, 2 * HOLD) == []  # once


def test_a_forged_return_is_refuted_by_the_nodes_report_and_never_released() -> None:
    gate = ReturnGate(HOLD, 10_000_000)
    gate.telemetry(tel(0), 0, 0)
    gate.hold(Return(1, 1, 65_535), 0, 1_000)  # forged: the node made no return
    assert gate.telemetry(tel(1, witness=0), 0, 2_000) == ([], [])  # a forged confirmation ...
    evidence, _ = gate.telemetry(tel(0, witness=2), 0, 30_000)  # ... and the genuine report
    assert any("2 frame(s) in its name" in line for line in evidence)
    assert any("contradicts itself" in line for line in evidence)
    assert gate.release(1, 0, 10 * HOLD) == []
    assert gate.status(1)["returns_refuted"] == 1
    assert gate.blocked(1, 40_000) and not gate.blocked(1, 10_030_000)


def test_a_confirmation_that_arrives_after_the_hold_does_not_release_at_once() -> None:
    """Found in review: the hold counted from the RETURN let a forged TELEMETRY sent after it
    release a forged RETURN in the same step, before the node could refute it."""
    gate = ReturnGate(HOLD, 10_000_000)
    gate.telemetry(tel(0), 0, 0)
    gate.hold(Return(1, 1, 1_000), 0, 1_000)
    gate.telemetry(tel(1), 0, 10 * HOLD)  # forged, long after the RETURN
    assert gate.release(1, 0, 10 * HOLD) == []
    evidence, _ = gate.telemetry(tel(0, witness=2), 0, 10 * HOLD + 30_000)  # the node refutes
    assert evidence and gate.release(1, 0, 20 * HOLD) == []


def test_a_restart_or_a_first_report_is_no_evidence_but_a_count_that_moves_is() -> None:
    gate = ReturnGate(HOLD, 10_000_000)
    assert gate.telemetry(tel(0, witness=3), 0, 0) == (
        [],
        ["the node reports 3 frame(s) in its name since it started"],
    )  # this supervisor cannot tell when
    assert gate.telemetry(tel(0, witness=0), 0, 1) == (
        [],
        ["the node's witness count went back: it restarted"],
    )
    evidence, _ = gate.telemetry(tel(0, witness=128), 0, 2)  # at most 128 between two reports
    assert evidence == ["the node saw 128 frame(s) in its name that it did not send"]
    joining = Telemetry(1, 0, Telemetry.JOINING, 0, 7)
    assert gate.telemetry(joining, 0, 3) == ([], [])  # no books: nothing to compare
    assert gate.nodes[1].evidence_at == 2 and gate.blocked(1, 2)  # only the count that moved


def test_a_node_reports_before_its_witness_count_could_turn_over(tmp_path: Path) -> None:
    """256 frames in a node's name between two of its wakeups would leave its 8-bit count where
    it was: the node reports at once after 128 (so does the C node, in lockstep)."""
    node = FirmwareNode(1, NvStore(tmp_path / "1.nv", 1, fsync=False), NodeConfig(), 0)
    host = NodeHost([node])
    node.on_wakeup(0)  # the boot-up report
    arbitration_id, data = Codec().encode(Return(1, 1, 1_000))
    reports = []
    for i in range(256):
        frame = can.Message(arbitration_id=arbitration_id, data=data, timestamp=i)
        reports += host.on_foreign_direction(frame, 10 + i)
    assert [r.witness for r in reports] == [WITNESS_REPORT_AT, 0]  # 128, then 256 mod 256


def test_two_returns_with_one_number_are_evidence() -> None:
    gate = ReturnGate(HOLD, 10_000_000)
    gate.hold(Return(1, 1, 500), 0, 0)
    assert gate.hold(Return(1, 1, 500), 0, 10) is None  # a resent one: the same
    assert "two RETURNs numbered 1" in (gate.hold(Return(1, 1, 900), 0, 20) or "")


def test_returns_acknowledged_by_someone_else_resynchronise_at_0_mj() -> None:
    gate = ReturnGate(HOLD, 10_000_000)
    gate.hold(Return(1, 3, 800), 1, 0)  # the supervisor credited 1; the node is at 3
    gate.telemetry(tel(3), 1, 10_000)
    assert gate.release(1, 1, 10_000 + HOLD) == [Return(1, 2, 0), Return(1, 3, 800)]
    assert gate.status(1)["returns_resynchronised"] == 1


@pytest.mark.parametrize(
    "command", [["supervisor", "--nodes", "1"], ["gateway", "--node", "9", "--nodes", "1"]]
)
def test_a_return_hold_too_short_for_the_node_to_refute_is_refused(
    command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """rv3 F4: ``--return-hold 1ms`` credited a forged RETURN before the node's report (3 ms
    later) arrived. Below ``RETURN_HOLD_MIN_US`` (100 ms) the flag and the typed config refuse."""
    base = [*command, "--state", "s.json"]
    for short in ("1ms", "99.999ms"):
        with pytest.raises(SystemExit) as exit_:
            build_parser().parse_args([*base, "--return-hold", short])
        assert exit_.value.code == 2
        err = capsys.readouterr().err.splitlines()[-1]
        assert "--return-hold" in err and "less than 100ms" in err, err
    args = build_parser().parse_args([*base, "--return-hold", "100ms"])
    assert args.return_hold == RETURN_HOLD_MIN_US == 100_000
    with pytest.raises(ValueError, match="less than 100000"):
        ServiceConfig(return_hold_us=RETURN_HOLD_MIN_US - 1)
    assert ServiceConfig(return_hold_us=RETURN_HOLD_MIN_US).return_hold_us == 100_000
    assert ServiceConfig().return_hold_us is None  # with a key: no hold


def test_the_least_hold_outlasts_the_refutation_of_rv3() -> None:
    """rv3's experiment: a forged RETURN of 65.535 J and a forged TELEMETRY confirming it, the
    node's refutation 3 ms later. The least hold still holds it at the supervisor's next passes,
    and the refutation drops it."""
    gate = ReturnGate(RETURN_HOLD_MIN_US, 10_000_000)
    gate.telemetry(tel(0), 0, 0)
    gate.hold(Return(1, 1, 65_535), 0, 1_000)  # forged
    gate.telemetry(tel(1), 0, 2_000)  # forged confirmation
    assert gate.release(1, 0, 3_000) == []
    evidence, _ = gate.telemetry(tel(0, witness=2), 0, 5_000)  # the node's refutation
    assert evidence and gate.release(1, 0, 10 * RETURN_HOLD_MIN_US) == []


def test_the_service_credits_a_resynchronised_return_and_reports_the_gap() -> None:
    rig = Harness("hardened")
    rig.begin(1_000_000)
    rig.settle()  # 1 J delivered to node 1
    core = rig.sup
    config = ServiceConfig(return_hold_us=HOLD, fsync=False, status_period_us=10**12)
    service = build_service(core, config, 0)
    service.on_message(tel(0), 0)
    service.on_message(Return(1, 2, 400), 1_000)  # return 1 was acked in its name meanwhile
    service.on_message(tel(2), 2_000)
    assert core.session(1).returns_credited == 0  # held
    out = service.on_wakeup(HOLD + 2_000)
    assert core.session(1).returns_credited == 2 and core.session(1).returned == 400_000
    assert ReturnAck(1, 2) in out
    (gap,) = [e for e in service.intrusions.as_json()["recent"] if "resynchronised" in e["kind"]]
    assert gap["node"] == 1 and service.intrusions.total == 1  # someone else's doing


class Wire:
    """A supervisor service and an emulated node joined by hand, time driven explicitly: each
    frame reaches the other side at once, and the node sees a rogue's frame in its name as its
    bus loop hands it over (``on_foreign_direction``)."""

    def __init__(self, tmp: Path) -> None:
        config = ServiceConfig(return_hold_us=HOLD, fsync=False, status_period_us=10**12)
        self.service = build_service(Supervisor((1,), 10_000_000), config, 0)
        nv = NvStore(tmp / "1.nv", 1, fsync=False)
        self.node = FirmwareNode(1, nv, NodeConfig(telemetry_period_us=1_000_000), 0)
        self.host = NodeHost([self.node])
        self.held: list[ToClient] = []
        """Frames to the node kept back (``hold_down``): a transaction in flight."""
        self.hold_down = False

    def run(self, now: int, up: list[Message] | None = None) -> None:
        """Deliver ``up`` and every frame it causes, then what falls due at ``now``."""
        up = list(up or [])
        while True:
            down: list[Message] = []
            for msg in up:
                down += self.service.on_message(msg, now)
            if (due := self.service.next_wakeup()) is not None and due <= now:
                down += self.service.on_wakeup(now)
            up = []
            for msg in down:
                assert isinstance(msg, ToClient)
                if self.hold_down:
                    self.held.append(msg)
                else:
                    up += self.host.on_message(msg, now)
            if (wake := self.host.next_wakeup()) is not None and wake <= now:
                up += self.host.on_wakeup(now)
            if not up:
                return

    def forge(self, msg: Message, now: int) -> None:
        """A rogue's frame in the node's name: the supervisor takes it, the node sees it."""
        ident, data = Codec().encode(msg)
        frame = can.Message(arbitration_id=ident, data=data)
        self.service.on_message(msg, now)
        reply = list(self.host.on_foreign_direction(frame, now))
        self.run(now, reply)

    def release(self, now: int) -> None:
        self.hold_down = False
        down, self.held = self.held, []
        up: list[Message] = []
        for msg in down:
            up += self.host.on_message(msg, now)
        self.run(now, up)

    def node_status(self) -> dict[str, int]:
        return dict(self.service.status()["nodes"]["1"])


def test_a_forged_join_is_refuted_on_the_frame_and_writes_nothing_off(tmp_path: Path) -> None:
    """Issue 40, item 11: a forged JOIN (and a forged TELEMETRY without books confirming it)
    wrote off the grant in flight at once. The JOIN is now held: the node sees both frames in
    its name and reports with its books, which drops the JOIN; the intrusion is raised at once,
    or here ``WITNESS_GAP_US`` later (the node's periodic report left at the very time of the
    forgery: two nodes on one id must not answer each other's reports with no pause), not a
    telemetry period later, and well inside the JOIN's hold."""
    w = Wire(tmp_path)
    w.run(0)  # the new node's JOIN and its TELEMETRY without books: held ...
    assert w.node.joining and w.node_status()["admitted"] == 0
    w.run(JOIN_HOLD_US - 1)
    assert w.node.joining
    w.run(JOIN_HOLD_US)  # ... admitted once the hold is over, nobody having objected
    assert not w.node.joining and w.node_status()["admitted"] == 1

    replies: list[dict[str, object]] = []
    w.service.request_grant(1, 1_000_000, replies.append)
    w.hold_down = True  # its INTENTION in flight when the rogue speaks
    t = 2_000_000
    w.run(t)
    assert [type(m) for m in w.held] == [Intention]
    assert w.node.telemetry_sent == 3 and w.node.next_telemetry == t + 1_000_000  # one at t
    w.forge(Join(1, 0x1234), t)
    w.forge(Telemetry(1, 0, Telemetry.JOINING, 0, 0), t)
    assert w.service.intrusions.as_json()["first_at_us"] is None
    w.run(t + WITNESS_GAP_US - 1)
    assert w.service.intrusions.as_json()["first_at_us"] is None
    w.run(t + WITNESS_GAP_US)
    report = w.service.intrusions.as_json()
    assert report["first_at_us"] == t + WITNESS_GAP_US  # a gap after its last report
    assert any("frame(s) in its name" in e["kind"] for e in report["recent"])
    assert any("forged or replayed" in e["kind"] for e in report["recent"])
    w.run(t + 10 * JOIN_HOLD_US)
    w.release(t + 10 * JOIN_HOLD_US)
    assert replies == [{"node": 1, "tx": 1, "outcome": "COMMITTED", "amount_uj": 1_000_000}]
    status = w.node_status()
    assert status["admitted"] == 1 and status["written_off"] == 0
    assert w.node.client.state.usable == 1_000_000


def test_a_forged_telemetry_is_raised_on_the_frame_not_a_period_later(tmp_path: Path) -> None:
    """Issue 40, item 11: a forged TELEMETRY ("empty: top me up") is raised when it is sent,
    not at the node's next periodic report (1 s here): the node sees it in its name and reports
    at once; the supervisor raises on that report and tops the node up no more."""
    w = Wire(tmp_path)
    w.run(0)
    w.run(JOIN_HOLD_US)
    t = JOIN_HOLD_US + 300_000  # well inside the node's telemetry period
    w.forge(Telemetry(1, 0, 0, 0, w.node.witnessing.reported), t)  # copies its count
    assert w.service.intrusions.as_json()["first_at_us"] == t
    assert w.service.witness.blocked(1, t)


def test_a_forged_join_while_the_node_is_off_writes_off_what_was_open(tmp_path: Path) -> None:
    """The residual: a node that is off cannot object, so a forged JOIN and TELEMETRY without
    books are admitted once the hold is over and what was open is written off (lost to the
    supervisor's books, never created: the node, back with its books, is paid it through Gs at
    its next intention)."""
    w = Wire(tmp_path)
    w.run(0)
    w.run(JOIN_HOLD_US)
    w.service.request_grant(1, 1_000_000, lambda reply: None)
    w.hold_down = True
    t = 2_000_000
    w.run(t)
    w.service.on_message(Join(1, 0x1234), t)  # the node is off: it sees nothing
    w.service.on_message(Telemetry(1, 0, Telemetry.JOINING, 0, 0), t)
    w.service.on_wakeup(t + JOIN_HOLD_US - 1)
    assert w.node_status()["written_off"] == 0
    w.service.on_wakeup(t + JOIN_HOLD_US)
    assert w.node_status()["admitted"] == 2 and w.node_status()["written_off"] == 1
    assert w.service.core.session(1).delivered == 1_000_000  # booked as delivered


@pytest.fixture
def guarded(tmp_path: Path) -> Iterator[Bench]:
    yield from bench(tmp_path, "--return-hold", "300ms")


def grant(b: Bench, amount_uj: int) -> None:
    answer = b.sup.grant(1, amount_uj)
    assert answer.get("outcome") == "COMMITTED", answer


def supervisor_intrusions(b: Bench) -> int:
    return int(b.status().get("nodes", {}).get("1", {}).get("intrusions", 0))


def test_a_forged_return_is_never_credited_and_raised_within_a_second(guarded: Bench) -> None:
    b = guarded
    grant(b, 2_000_000)
    b.wait(lambda: b.status()["nodes"]["1"]["delivered_uj"] == 2_000_000)
    before = b.status()
    sent = b.forge(Return(1, 1, 1_000))  # no larger than what the node may hold
    b.wait(lambda: supervisor_intrusions(b) >= 1)
    assert b.status()["intrusion_report"]["first_at_us"] - sent < 1_000_000
    time.sleep(1.0)  # well past the hold
    after = b.status()
    assert after["nodes"]["1"]["returns_credited_uj"] == 0
    assert after["usable_uj"] == before["usable_uj"]  # nothing created
    assert b.host.nodes[1].witnessed >= 1


@pytest.fixture
def topped_up(tmp_path: Path) -> Iterator[Bench]:
    yield from bench(tmp_path, "--target", "1J", "--return-hold", "300ms")


def test_a_forged_telemetry_stops_the_nodes_top_ups(topped_up: Bench) -> None:
    b = topped_up
    b.wait(lambda: b.status()["nodes"]["1"]["delivered_uj"] >= 1_000_000)
    started = monotonic_us()
    start = time.monotonic()
    while time.monotonic() - start < 3:
        b.forge(Telemetry(1, 0, 0, 0, 0))  # "empty": top me up
        time.sleep(0.05)
    status = b.status()
    assert supervisor_intrusions(b) >= 1
    first = status["intrusion_report"]["first_at_us"]
    assert first is not None and first - started < 1_000_000
    assert status["nodes"]["1"]["delivered_uj"] <= 2_000_000  # not the whole 10 J


def test_a_forged_join_is_raised_by_the_supervisor(guarded: Bench) -> None:
    b = guarded
    # the supervisor judges the node's count once it has heard it with books (its baseline):
    # the node's TELEMETRY once admitted, sent before the forgery (the bus keeps the order)
    node = b.host.nodes[1]
    b.wait(lambda: not node.joining)
    admitted_at = node.telemetry_sent
    b.wait(lambda: node.telemetry_sent > admitted_at)
    sent = b.forge(Join(1, 0x1234))
    b.wait(lambda: supervisor_intrusions(b) >= 1)
    assert b.status()["intrusion_report"]["first_at_us"] - sent < 1_000_000
    assert any("in its name" in e["kind"] for e in b.status()["intrusion_report"]["recent"])


def test_a_forged_join_does_not_wipe_the_witness_baseline() -> None:
    """Found in CI: the ADMIT a forged JOIN draws reset the node's witness state, so the node's
    report of that very JOIN looked like a first report (logged, not raised)."""
    gate = ReturnGate(HOLD, 10_000_000)
    gate.telemetry(tel(3), 3, 0)
    gate.readmitted(1)  # the supervisor admitted "the node" again
    evidence, _ = gate.telemetry(tel(3, witness=1), 3, 10_000)
    assert evidence == ["the node saw 1 frame(s) in its name that it did not send"]


pytestmark = pytest.mark.usefixtures("both_cores")
"""Each test on the Python core and on the compiled one (tests/conftest.py)."""
