"""A Damiao motor's own watchdog, its CAN Timeout register (RID 9), sans-IO in explicit time:
the MIT gate (``canergy.devices.mit_gate``) reads it at set-up and again every ``REREAD_US``
(``--mit-max-watchdog``), against the emulated motor (``firmware_model.mit.motor``), which
enforces the timeout. A register changed behind the gate, or a read left unanswered, stops the
motor for good; unchanged, it runs on; once the host is gone the emulated motor disables itself
within its timeout, so what it draws stays within the status's ``after_exit_uj``."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from canergy.codec import Codec
from canergy.core import Supervisor, Timing
from canergy.devices.guard import REREAD_US, GuardPhase
from canergy.devices.mit import (
    CLEAR_ERROR,
    ENTER,
    EXIT,
    MODELS,
    TIMEOUT_RID,
    encode,
    pack_reply,
    read_register,
    unpack_reply,
)
from canergy.devices.mit_gate import LATE_WINDOW_US, MitGate
from canergy.live.devices.mit_motor import MitMotor, gate_for
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.policy import Limits as GrantLimits
from canergy.live.supervisor.policy import TopUp
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import Direction, Message, ToClient
from firmware_model.mit.motor import LOST_COMM, MitMotorModel

DM = MODELS["DM4310"]
MOTOR, NODE = 1, 11
KIND = "DM4310: the CAN Timeout register (RID 9)"
TIMEOUT = 2000
"""The emulated motor's CAN Timeout: 2000 × 50 µs = 0.1 s."""
PUSH = encode(DM, 0.0, 0.0, 0.0, 0.0, 10.0).pack()
"""The largest feed-forward torque (clamped to the 0.5 N·m cap: it runs the motor up to speed)."""
STEP = 1_000


class Bench:
    """A supervisor service granting to the gate of ``MOTOR``, in line before the emulated
    DM4310 (its CAN Timeout ``can_timeout``), stepped in ``STEP`` µs; the application enters
    motor mode and pushes once the budget is granted (the gate holds the command since)."""

    def __init__(self, can_timeout: int = TIMEOUT, max_watchdog_us: int | None = 1_000_000):
        timing = Timing(response_timeout_us=20_000)
        config = {"max_watchdog_us": max_watchdog_us, "feedback_timeout_us": 300_000}
        self.gate: MitGate = gate_for(MitMotor(MOTOR, NODE, max_torque=0.5), 0, timing, config)
        self.motor = MitMotorModel(MOTOR, DM, 0, master_id=MOTOR + 0x10, can_timeout=can_timeout)
        self.codec = Codec()
        self.service = build_service(
            Supervisor((NODE,), 10**9, timing=timing),
            ServiceConfig(
                policy=TopUp(5_000_000),
                limits=GrantLimits(max_grant=5_000_000),
                fsync=False,
                status_period_us=10**12,
                join_hold_us=0,
            ),
            0,
        )
        self.now = 0
        self.reads: list[int] = []
        """When each 0x7FF read went out."""
        self.answer: Callable[[bytes], list[bytes]] = self.register
        """What the motor's side answers a 0x7FF frame with (default: the emulator)."""
        self.pushed = False
        self.refused_at: int | None = None
        self.held: list[bytes] = []
        """Frames from the master id held back until after the motor's next reply."""
        self.next_reply: bytes | None = None
        """What the motor's next reply is replaced with (once)."""

    def register(self, data: bytes) -> list[bytes]:
        reply = self.motor.register(data)
        return [] if reply is None else [reply]

    def route(self, up: list[Message], now: int) -> None:
        todo: deque[tuple[Direction, Message]] = deque((Direction.TO_SUPERVISOR, m) for m in up)
        while todo:
            direction, msg = todo.popleft()
            wire = self.codec.decode(*self.codec.encode(msg), direction=direction)
            if direction is Direction.TO_SUPERVISOR:
                todo.extend((Direction.TO_CLIENT, m) for m in self.service.on_message(wire, now))
            else:
                assert isinstance(wire, ToClient)
                todo.extend((Direction.TO_SUPERVISOR, m) for m in self.gate.on_message(wire, now))

    def to_motor(self, data: bytes, t: int) -> None:
        reply = self.motor.receive(data)
        if self.next_reply is not None:
            reply, self.next_reply = self.next_reply, None
        self.route(self.gate.from_motor(reply, t, t), t)
        held, self.held = self.held, []
        for frame in held:
            self.route(self.gate.from_motor(frame, t, t), t)

    def run_to(self, until: int) -> None:
        gate = self.gate
        while self.now < until:
            t = self.now = self.now + STEP
            self.motor.advance(t)
            up = gate.on_wakeup(t) if gate.next_wakeup() <= t else []
            wakeup = self.service.next_wakeup()
            if wakeup is not None and wakeup <= t:
                self.route(list(self.service.on_wakeup(t)), t)
            self.route(up, t)
            for data in gate.take_parameter_frames():
                self.reads.append(t)
                for answer in self.answer(data):
                    self.route(gate.from_motor(answer, t, t), t)
            for data in gate.take_frames():
                self.to_motor(data, t)
            if not self.pushed and gate.guard.phase is GuardPhase.RUNNING:
                self.pushed = True
                for data in (ENTER, PUSH):
                    verdict = gate.from_app(data, t)
                    assert verdict.frame is not None, verdict
                    self.to_motor(verdict.frame, t)
            if self.refused_at is None and gate.guard.refused is not None:
                self.refused_at = t

    def watchdog(self) -> dict[str, object]:
        return dict(self.gate.status(self.now)["watchdog"])


def running(bench: Bench, until: int = 3_000_000) -> None:
    bench.run_to(until)
    g = bench.gate.guard
    assert g.phase is GuardPhase.RUNNING and g.refused is None, g.stop_reason
    assert bench.pushed and bench.motor.enabled and bench.motor.torque_max_seen > 0.4


def test_an_unchanged_register_is_read_every_second_and_the_motor_runs_on() -> None:
    bench = Bench()
    running(bench, 6_000_000)
    # asked at set-up (time 0, on the bus with the first step), then every second
    assert bench.reads == [STEP, *(k * REREAD_US for k in range(1, 7))]
    w = bench.watchdog()
    assert w["state"] == "armed" and w["timeout_s"] == 0.1 and w["changes"] == 0
    assert w["reads"] == 7 and w["verified_age_us"] == 0
    assert bench.motor.timeouts == 0  # the gate's frames every 20 ms keep it fed


def test_a_register_set_to_off_behind_the_gate_stops_the_motor_within_a_period() -> None:
    """A USB tool sets the CAN Timeout to 0 while the motor runs: the next read shows it, and
    the motor is stopped for good (exit motor mode), as for any refusal."""
    bench = Bench()
    running(bench)
    changed = bench.now + 500
    bench.run_to(changed)
    bench.motor.can_timeout = 0
    bench.run_to(changed + REREAD_US + LATE_WINDOW_US + 100_000)
    assert bench.refused_at is not None and bench.refused_at - changed <= REREAD_US + STEP
    g = bench.gate.guard
    assert g.refused == (
        "watchdog changed behind the guard (a periodic read-back): off (disabled), was "
        "enabled, timeout 0.1 s"
    )
    assert g.phase is GuardPhase.STOPPED and g.latched and not bench.motor.enabled
    w = bench.watchdog()
    assert w["state"] == "off" and w["changes"] == 1 and w["after_exit"] == "unbounded"
    assert g.watchdog is not None and g.watchdog.note() == f"refused: {g.refused}"
    assert bench.reads[-1] == bench.refused_at  # and not read again: stopped for good
    assert bench.gate.from_app(ENTER, bench.now).frame is None


def test_a_register_read_left_unanswered_stops_the_motor_two_seconds_after_it() -> None:
    bench = Bench()
    running(bench)
    silent = bench.now + 500
    bench.run_to(silent)
    bench.answer = lambda data: []
    bench.run_to(silent + REREAD_US + LATE_WINDOW_US + 100_000)
    asked = min(t for t in bench.reads if t > silent)
    assert bench.refused_at == asked + LATE_WINDOW_US  # the read's deadline, a wakeup of its own
    assert bench.refused_at - silent <= REREAD_US + LATE_WINDOW_US
    g = bench.gate.guard
    assert g.refused == f"watchdog not read back: a periodic read-back unanswered ({KIND})"
    assert g.phase is GuardPhase.STOPPED and not bench.motor.enabled
    w = bench.watchdog()
    assert w["state"] == "unanswered" and w["verified"] is False and w["changes"] == 0
    assert w["verified_age_us"] == bench.now - (asked - REREAD_US)  # the last answered read


def test_a_reply_that_looks_like_the_answer_does_not_hide_the_answer_behind_it() -> None:
    """A reply of the motor out of motor mode near -12.5 rad can start as the register's
    answer does (id, 0x33, 9). Here the motor's reply to the gate's next frame after a read is
    one, and the register's answer (set to 0 behind the gate) comes after it: the look-alike
    is taken for the answer (its bytes an armed 400 µs timeout), and the real answer is still
    judged, not taken as the reply to that frame: the motor is stopped."""
    look_alike = pack_reply(DM, MOTOR, 0x0033, 0x090, 0x800)
    assert look_alike[:4] == read_register(MOTOR, TIMEOUT_RID)[:4]
    assert int.from_bytes(look_alike[4:], "little") == 8  # 8 × 50 µs
    assert unpack_reply(DM, look_alike).p < -12.4
    bench = Bench()
    running(bench)
    bench.motor.can_timeout = 0

    def behind_a_look_alike(data: bytes) -> list[bytes]:
        bench.held += bench.register(data)
        bench.next_reply = look_alike
        return []

    bench.answer = behind_a_look_alike
    bench.run_to(bench.now + REREAD_US + 100_000)
    g = bench.gate.guard
    assert g.refused is not None and g.refused.startswith(
        "watchdog changed behind the guard (a periodic read-back): off (disabled), was enabled"
    )
    assert g.watchdog is not None and g.watchdog.changes == 2
    assert bench.gate.counts.unasked == 0  # neither taken as a reply nothing asked for


def test_without_the_flag_the_register_is_never_read() -> None:
    bench = Bench(max_watchdog_us=None)
    running(bench)
    assert bench.reads == [] and bench.watchdog()["state"] == "not read"


def test_the_emulated_motor_disables_itself_when_frames_stop_for_longer_than_its_timeout() -> None:
    motor = MitMotorModel(MOTOR, DM, 0, master_id=MOTOR + 0x10, can_timeout=TIMEOUT)
    t = 0
    for data in (ENTER, PUSH):
        motor.receive(data)
    for _ in range(10):  # a frame every 99 ms: within the timeout
        t += 99_000
        motor.advance(t)
        assert motor.enabled, t
        motor.receive(PUSH)
    assert motor.timeouts == 0 and motor.motor.omega > 1
    motor.advance(t + TIMEOUT * 50)  # exactly the timeout: not yet
    assert motor.enabled
    motor.advance(t + TIMEOUT * 50 + STEP)
    assert not motor.enabled and motor.fault == LOST_COMM and motor.timeouts == 1
    t += TIMEOUT * 50 + 2 * STEP
    motor.advance(t)  # a step without current
    reply = unpack_reply(DM, motor.receive(ENTER))  # latched: enter does not re-enable it
    assert reply.state == LOST_COMM and not motor.enabled and abs(reply.torque) < 0.01
    motor.receive(CLEAR_ERROR)
    assert unpack_reply(DM, motor.receive(ENTER)).state == 1 and motor.enabled
    off = MitMotorModel(MOTOR, DM, 0, can_timeout=0)
    for data in (ENTER, PUSH):
        off.receive(data)
    off.advance(10_000_000)
    assert off.enabled and off.timeouts == 0  # 0: off
    stays = MitMotorModel(MOTOR, DM, 0, can_timeout=TIMEOUT)
    stays.receive(EXIT)
    stays.advance(10_000_000)  # not enabled: nothing counted
    assert stays.fault == 0 and stays.receive(ENTER) and stays.enabled


def test_once_the_host_is_gone_the_motor_draws_no_more_than_the_status_said() -> None:
    """The status's ``after_exit_uj`` (the model's whole envelope times the timeout read back)
    bounds what the emulated motor draws after the gate's process died mid-command: it disables
    itself 0.1 s after the last frame. Without its timeout it would push on (about 4.5 W at 30 rad/s
    under the 0.5 N·m cap: 90 J over the 20 s here)."""
    bench = Bench()
    running(bench)
    after_exit = bench.watchdog()["after_exit_uj"]
    assert isinstance(after_exit, int) and 44e6 < after_exit < 44.4e6  # 442.77 W × 0.1 s
    drawn = bench.motor.drawn_uj
    gone = bench.now
    bench.motor.advance(gone + 20_000_000)  # nothing feeds it any more
    assert not bench.motor.enabled and bench.motor.fault == LOST_COMM
    assert 0 < bench.motor.drawn_uj - drawn <= after_exit
    assert bench.motor.timeouts == 1
    assert bench.motor.torque_max_seen <= 0.5 + 1e-9
