"""A node's NV record put back from an older copy (a backup, an image flashed over a newer
record), on the live stack: `canergy supervisor` as users run it and the emulated node on
python-can's virtual bus. Under the hardened rules the older record gets back what its actuator
already used (paid back as if written off); under ``--variant witnessed`` the supervisor finds it
behind and admits it afresh, with and without ``--auth``: nothing is created.

What the actuators used is counted across both lives (each life's ``drawn_uj``: the older
record's own ``spent`` went back with it, which is why the node's books alone cannot show it).
"""

from __future__ import annotations

import json
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.auth.frames import AuthFailure, FrameAuth, Layout, expected_freshness
from canergy.auth.keys import load_key
from canergy.ccore.supervisor import CompiledSupervisor
from canergy.cli import main
from canergy.codec import Codec
from canergy.core import ClientState, Send, Supervisor, Timing
from canergy.core.state import Session, SupervisorState
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.control import request
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.state_file import load_state, save_state
from canergy.messages import SYNC_CONFIRMED, Admit, Debit, Direction, ReturnAck, Telemetry
from canergy.units import UJ_PER_J
from firmware_model.__main__ import bind_starts
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

NODE = 1
CODEC = Codec()
TIMING = Timing(response_timeout_us=100_000, retries=3, command_timeout_us=200_000)


@dataclass
class Bench:
    tmp: Path
    channel: str
    variant: str
    auth: Layout | None
    thread: threading.Thread
    result: list[int]

    def status(self) -> dict[str, Any]:
        try:
            data: dict[str, Any] = json.loads((self.tmp / "status.json").read_text())
            return data
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    def node_status(self) -> dict[str, Any]:
        found: dict[str, Any] = self.status().get("nodes", {}).get(str(NODE), {})
        return found

    def start_node(self) -> tuple[FirmwareNode, Loop]:
        """One life of the node, from whatever its NV file holds now."""
        config = NodeConfig(
            power=PowerProfile.constant(0.5),
            telemetry_period_us=100_000,
            timing=TIMING,
            variant=self.variant,
        )
        node = FirmwareNode(
            NODE, NvStore(self.tmp / "node.nv", NODE, fsync=False), config, monotonic_us()
        )
        host = NodeHost([node])
        auth = None
        if self.auth is not None:
            key = load_key(self.tmp / "n1.key").node_key(NODE)
            auth = FrameAuth(CODEC, self.auth, lambda n: key, Direction.TO_CLIENT, host.freshness)
            bind_starts(auth, host)
        bus = can.Bus(
            interface="virtual",
            channel=self.channel,
            fd=self.auth is Layout.FD,
            can_filters=CODEC.client_watch_filters(NODE),
        )
        runtime = BusRuntime(bus, host, codec=CODEC, receives=Direction.TO_CLIENT, auth=auth)
        return node, Loop(runtime)

    def stop_supervisor(self) -> dict[str, Any]:
        request(self.tmp / "ctl.sock", {"stop": True}, 30)
        self.thread.join(timeout=60)
        assert self.result == [0]
        return self.status()


def wait(condition: Any, timeout_s: float = 60.0) -> None:
    """Until ``condition()``; the loops run on the wall clock, so the bound is generous."""
    done = threading.Event()
    deadline = monotonic_us() + int(timeout_s * 1e6)
    while not condition():
        assert monotonic_us() < deadline, f"condition not met within {timeout_s} s"
        done.wait(0.02)


def bench(
    tmp: Path,
    variant: str,
    auth: Layout | None,
    channel: str | None = None,
    core: str = "python",
    extra: tuple[str, ...] = (),
) -> Bench:
    """A supervisor on ``core`` started on ``channel`` (default: a new one) with ``extra``
    flags, its keys made once."""
    channel = channel or f"oldcopy-{uuid.uuid4().hex}"
    argv = [
        "supervisor",
        *("-i", "virtual", "-c", channel, "--variant", variant, "--core", core),
        *("--nodes", str(NODE), "--initial", "50J", "--target", "1J", "--max-grant", "0.5J"),
        *("--state", str(tmp / "s.json"), "--no-fsync", "--response-timeout", "100ms"),
        *("--status-file", str(tmp / "status.json"), "--status-period", "50ms"),
        *("--control", str(tmp / "ctl.sock")),
        *extra,
    ]
    if auth is not None and not (tmp / "m.key").exists():
        assert main(["keys", "-o", str(tmp / "m.key")]) == 0
        keys = ["keys", "--master", str(tmp / "m.key"), "--nodes", "1", "-o", str(tmp / "n1.key")]
        assert main(keys) == 0
    if auth is not None:
        argv += ["--auth", str(tmp / "m.key"), *(["--fd"] if auth is Layout.FD else [])]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    return Bench(tmp, channel, variant, auth, thread, result)


def released(session: dict[str, Any]) -> int:
    """All the supervisor's books let go to the node: delivered (committed and written off)
    and reserved, less what it credited back."""
    return int(session["delivered_uj"] + session["reserved_uj"] - session["returns_credited_uj"])


def held(node: FirmwareNode) -> int:
    """What the node still holds: its budget, a draw on the way, what its actuator may use."""
    c = node.client.state
    return c.usable + c.return_pending + node.ready_uj


def restored_older_copy(b: Bench) -> tuple[FirmwareNode, FirmwareNode, Loop]:
    """Life 1 spends; its NV file is copied; it spends 1 J more and loses power; the copy is
    put back and life 2 starts from it."""
    first, loop = b.start_node()
    wait(lambda: b.node_status().get("committed", 0) >= 3 and first.actuator.drawn_uj >= UJ_PER_J)
    copy = (b.tmp / "node.nv").read_bytes()
    at_copy = first.actuator.drawn_uj
    wait(lambda: first.actuator.drawn_uj >= at_copy + UJ_PER_J)
    loop.halt()  # power lost: only the NV file survives
    (b.tmp / "node.nv").write_bytes(copy)
    second, loop = b.start_node()
    return first, second, loop


@pytest.mark.parametrize("auth", [None, *Layout], ids=["no key", "auth classic", "auth fd"])
@pytest.mark.parametrize("core", ["python", "c"])
def test_an_older_copy_of_a_nodes_record_creates_nothing_under_witnessed(
    tmp_path: Path, core: str, auth: Layout | None, caplog: pytest.LogCaptureFixture
) -> None:
    b = bench(tmp_path, "witnessed", auth, core=core)
    first, second, loop = restored_older_copy(b)
    try:
        assert second.resumes == 1  # started RESUMING (its loop may have its ADMIT already)
        wait(lambda: second.found_behind == 1 and not second.resuming)
        status = b.node_status()
        wait(lambda: b.node_status().get("found_behind") == 1)
        committed = b.node_status()["committed"]
        wait(lambda: b.node_status()["committed"] >= committed + 3)  # it runs on, afresh
        wait(lambda: second.actuator.drawn_uj >= UJ_PER_J // 2)
    finally:
        loop.halt()
    final = b.stop_supervisor()["nodes"][str(NODE)]
    used = first.actuator.drawn_uj + second.actuator.drawn_uj + held(second)
    assert used <= released(final), (used, released(final), status)
    assert final["found_behind"] == 1 and final["resumes"] >= 1
    assert second.status()["found_behind"] == 1 and second.dropped_uj > 0
    said = caplog.text
    assert "RESUMING" in said and "older than the supervisor's: admitted afresh" in said
    assert "started from a record older than the books" in said


@pytest.mark.parametrize("core", ["python", "c"])
def test_a_copy_taken_while_the_nodes_start_waits_for_the_supervisor_creates_nothing(
    tmp_path: Path, core: str
) -> None:
    """protocol.md, 2' (i), on the live stack: the node spends, then both stop; the node comes
    on first and its start waits for the supervisor (RESUME unanswered); its NV file is copied
    then (the record it began from); the supervisor comes on, confirms it and grants go on; the
    node loses power and the copy is put back: found behind, it runs on afresh and nothing is
    created."""
    b = bench(tmp_path, "witnessed", None, core=core)
    first, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("committed", 0) >= 2)
    finally:
        loop.halt()
    b.stop_supervisor()
    second, loop = b.start_node()  # the supervisor off: its start waits
    try:
        wait(lambda: second.resuming and second.resumes == 1)
        copy = (tmp_path / "node.nv").read_bytes()
        (tmp_path / "status.json").unlink()
        b = bench(tmp_path, "witnessed", None, b.channel, core)
        wait(lambda: not second.resuming and b.node_status().get("committed", 0) >= 3)
        wait(lambda: second.actuator.drawn_uj >= UJ_PER_J // 2)
    finally:
        loop.halt()  # power lost: only the NV file survives, put back to the copy
    (tmp_path / "node.nv").write_bytes(copy)
    third, loop = b.start_node()
    try:
        wait(lambda: third.found_behind == 1 and not third.resuming)
        committed = b.node_status()["committed"]
        wait(lambda: b.node_status()["committed"] >= committed + 2)  # it runs on, afresh
    finally:
        loop.halt()
    final = b.stop_supervisor()["nodes"][str(NODE)]
    used = sum(n.actuator.drawn_uj for n in (first, second, third)) + held(third)
    assert used <= released(final), (used, released(final))
    assert final["found_behind"] == 1 and third.dropped_uj > 0  # the copy's Uc dropped


def test_the_same_restore_under_the_hardened_rules_creates_energy(tmp_path: Path) -> None:
    """The measurement the witnessed rules answer: the older record is paid back what the node
    received after the copy, and its actuator uses it a second time."""
    b = bench(tmp_path, "hardened", None)
    first, second, loop = restored_older_copy(b)
    try:

        def created() -> int:
            session = b.node_status()
            used = first.actuator.drawn_uj + second.actuator.drawn_uj + held(second)
            return used - released(session) if session else 0

        wait(lambda: created() >= UJ_PER_J // 2)
    finally:
        loop.halt()
    b.stop_supervisor()


# --- without a key: a RESUME's pending return is held as a RETURN is ------------------------

HOLD = 300_000


def _service() -> SupervisorService:
    """A witnessed supervisor whose books let node 1 hold 1 J, holding returns for ``HOLD``."""
    state = SupervisorState(
        10 * UJ_PER_J, 9 * UJ_PER_J, sessions=(Session(NODE, delivered=UJ_PER_J),)
    )
    core = Supervisor([NODE], 10 * UJ_PER_J, variant="witnessed", timing=TIMING, state=state)
    return build_service(core, ServiceConfig(return_hold_us=HOLD), 0)


def resume(amount_mj: int, nonce: int = 7) -> Debit:
    """RESUME: started with debit 1 pending, a return of ``amount_mj`` (the next number)."""
    return Debit(NODE, nonce, Debit.START, 1, amount_mj)


def test_a_forged_resume_is_refuted_by_the_nodes_report_and_credits_nothing() -> None:
    """Without a key anyone can send a RESUME claiming a pending return numbered next; credited
    at once (as the core alone does) it is a forged RETURN. Held, the genuine node refutes it."""
    s = _service()
    s.on_message(Telemetry(NODE, 1000, 0, 0, 0), 0)
    assert s.on_message(resume(500), 1_000) == []  # held: no ADMIT, nothing credited
    assert s.status()["nodes"]["1"]["resume_waiting"] is True
    s.on_message(Telemetry(NODE, 1000, 0, 0, 1), 20_000)  # the node saw a frame in its name
    for now in (HOLD, 3 * HOLD):
        assert not any(isinstance(m, Admit) for m in s.on_wakeup(now))
    assert s.core.session(NODE).returned == 0 and s.core.session(NODE).returns_credited == 0
    assert s.intrusions.total >= 1
    assert s.status()["nodes"]["1"]["resume_waiting"] is False  # refuted: grants go on


@pytest.mark.parametrize("core", ["python", "c"])
def test_a_hardened_supervisor_takes_a_debit_for_what_its_rules_make_of_it(core: str) -> None:
    """The hardened rules have no DEBIT (their table ignores it). A RESUME or a SYNC's counts
    sent to a hardened supervisor, by a node on other rules or by anyone, must not be held as a
    witnessed one is (which withheld the node's grants and reset the return number its reports
    are judged by), nor counted as a resume or a node found behind: nothing moves."""
    state = SupervisorState(
        10 * UJ_PER_J, 9 * UJ_PER_J, sessions=(Session(NODE, delivered=UJ_PER_J),)
    )
    kind = Supervisor if core == "python" else CompiledSupervisor
    rules = kind([NODE], 10 * UJ_PER_J, variant="hardened", timing=TIMING, state=state)
    s = build_service(rules, ServiceConfig(return_hold_us=HOLD), 0)
    s.on_message(Telemetry(NODE, 1000, 0, 0, 0), 0)
    before = s.core.session(NODE)
    for now, debit in enumerate((resume(500), resume(0, 9), Debit.counts(NODE, 5, 1, 64)), 1):
        assert s.on_message(debit, now * 1_000) == []
    node = s.status()["nodes"]["1"]
    assert node["resume_waiting"] is False and node["resumes"] == 0
    assert node["found_behind"] == 0 and node["counts_ignored"] == 0
    assert s.core.session(NODE) == before and s.intrusions.total == 0


def test_a_genuine_resume_with_a_pending_return_is_credited_once_confirmed() -> None:
    s = _service()
    s.on_message(Telemetry(NODE, 500, 0, 0, 0), 0)
    assert s.on_message(resume(500), 1_000) == []
    s.on_message(Telemetry(NODE, 500, 0, 1, 0), 20_000)  # the node stands by debit 1
    assert s.on_wakeup(20_000 + HOLD - 1) == []
    out = s.on_wakeup(20_000 + HOLD)
    assert [m for m in out if isinstance(m, Admit)] == [Admit(NODE, 7, 0, 2)]  # 1 credited
    session = s.core.session(NODE)
    assert session.returned == 500_000 and session.returns_credited == 2
    assert s.status()["nodes"]["1"]["resumes"] == 1 and s.intrusions.total == 0


def test_the_last_resume_answered_survives_a_supervisor_restart(tmp_path: Path) -> None:
    """The last RESUME answered is in the state file; after a restart the supervisor answers
    nothing before its SYNC is answered (a RESUME re-sent meanwhile waits: the node answers the
    SYNC), and the node's books, confirmed before the restart, are confirmed again, not found
    behind (which would drop them)."""
    s = _service()
    s.on_message(Telemetry(NODE, 500, 0, 0, 0), 0)
    first = s.on_message(Debit(NODE, 9, Debit.START, 0, 0), 1_000)
    path = tmp_path / "s.json"
    save_state(path, s.core.state, "witnessed")
    state = load_state(path, "witnessed", (NODE,))
    assert state.sessions == s.core.state.sessions
    again = Supervisor([NODE], 10 * UJ_PER_J, variant="witnessed", timing=TIMING, state=state)
    again.power_loss(2_000, 0x77)
    assert first == [Admit(NODE, 9, 0, 1)]
    assert again.receive(Debit(NODE, 9, Debit.START, 0, 0), 3_000) == []
    again.receive(Debit.books(NODE, 0x77, 1_000), 3_100)
    counts = Debit.counts(NODE, 0x77, 1, TIMING.window)  # ltx settled a window ahead
    answer = [a.message for a in again.receive(counts, 3_200) if isinstance(a, Send)]
    assert answer == [Admit(NODE, 0x77 ^ SYNC_CONFIRMED, TIMING.window, 2)]  # debit 1 confirmed
    save_state(path, s.core.state, "hardened")
    assert "resume_to" not in path.read_text()


@pytest.mark.parametrize("layout", list(Layout))
def test_a_resume_and_its_admit_carry_32_bits_of_freshness(layout: Layout) -> None:
    """As a JOIN's: a RESUMING node draws 16 random bits above its nonce, the ADMIT's MAC binds
    them, and an ADMIT answering an earlier start with the same 16-bit nonce fails. A draw is
    fresh from its debit number: a replay older than the supervisor's count is stale."""
    key = bytes(range(16))

    def side(receives: Direction, seq: int) -> FrameAuth:
        return FrameAuth(
            CODEC, layout, lambda n: key, receives, lambda m: expected_freshness(m, 0, seq)
        )

    sup, node = side(Direction.TO_SUPERVISOR, 5), side(Direction.TO_CLIENT, 5)
    node.resume_fv[NODE] = 0xBEEF << 16 | 7
    resumed = Debit(NODE, 7, Debit.START, 5, 0)
    assert [v.message for v in map(sup.accept, node.frames(resumed))][-1] == resumed
    assert sup.resume_fv[NODE] == 0xBEEF0007
    admit = Admit(NODE, 7, 0, 6)
    assert [v.message for v in map(node.accept, sup.frames(admit))][-1] == admit
    earlier = side(Direction.TO_SUPERVISOR, 5)
    earlier.resume_fv[NODE] = 0x1234 << 16 | 7  # an earlier start, the same 16-bit nonce
    replayed = [node.accept(f) for f in earlier.frames(admit)][-1]
    assert replayed.failure is AuthFailure.MAC_BAD
    old_draw = side(Direction.TO_CLIENT, 4).frames(Debit(NODE, 0, Debit.DRAW, 4, 10))
    assert [sup.accept(f) for f in old_draw][-1].failure is AuthFailure.STALE


# --- the emulated node: the actuator runs on acknowledged draws only -------------------------


def test_the_actuator_runs_only_on_draws_the_supervisor_acknowledged(tmp_path: Path) -> None:
    """A witnessed node started with 1 J in its record: RESUMING, it draws nothing and its
    actuator gets nothing; confirmed, it draws one chunk (in NV, marked a draw, before the DEBIT
    leaves) and its actuator still gets nothing until the RETURN_ACK; then it runs."""
    nv = NvStore(tmp_path / "node.nv", NODE, fsync=False)
    nv.save(ClientState(NODE, usable=UJ_PER_J, credited=UJ_PER_J, last_tx=3, return_seq=4))
    config = NodeConfig(power=PowerProfile.constant(0.5), timing=TIMING, variant="witnessed")
    node = FirmwareNode(NODE, NvStore(tmp_path / "node.nv", NODE, fsync=False), config, 0)
    sent = node.on_wakeup(0)
    (start,) = [m for m in sent if isinstance(m, Debit)]
    assert start.is_resume and start.seq == 4 and node.resuming
    tick = config.tick_us
    assert not [m for m in node.on_wakeup(tick) if isinstance(m, Debit) and not m.is_resume]
    assert node.actuator.drawn_uj == 0 and node.actuator.halted
    draws = [
        m for m in node.on_message(Admit(NODE, start.nonce, 3, 5), tick + 1) if isinstance(m, Debit)
    ]
    assert draws == [Debit(NODE, 0, Debit.DRAW, 6, config.chunk() // 1000)]
    record = NvStore(tmp_path / "node.nv", NODE).load()
    assert record is not None and record.pending_draw and record.return_pending == config.chunk()
    node.on_wakeup(2 * tick)
    assert node.actuator.drawn_uj == 0  # drawn, not yet acknowledged
    node.on_message(ReturnAck(NODE, 6), 2 * tick + 1)
    node.on_wakeup(3 * tick)
    assert node.actuator.drawn_uj == 50_000 and not node.actuator.halted  # 0.5 W for 100 ms
    assert node.status()["draws"] >= 1 and node.status()["resumes"] == 1
