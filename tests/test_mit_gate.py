"""The in-line MIT gate (``canergy.devices.mit_gate``), sans-IO in explicit time, with a real
supervisor service granting to its proxy client: nothing reaches the motor without budget,
commands are clamped under the cap, the command in force is re-clamped when its hold expires,
the budget's end exits motor mode, and every refusal is counted."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from fractions import Fraction

from hypothesis import given, settings
from hypothesis import strategies as st

from canergy.cli import build_parser
from canergy.cli.inline import motors
from canergy.codec import Codec
from canergy.core import Supervisor, Timing
from canergy.devices.guard import DeviceConfig, GuardPhase
from canergy.devices.mit import (
    ENTER,
    EXIT,
    MODELS,
    SPECIAL,
    UNM_PER_NM,
    ZERO,
    Command,
    MitLimits,
    clamp,
    decode,
    encode,
    pack_reply,
    worst_torque,
)
from canergy.devices.mit_gate import LATE_WINDOW_US, REPLY_WINDOW_US, MitGate
from canergy.live.devices.mit_bus import gate_for
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.policy import Limits as GrantLimits
from canergy.live.supervisor.policy import TopUp
from canergy.live.supervisor.service import ServiceConfig
from canergy.messages import Direction, Message, ToClient

DM = MODELS["DM4310"]
NODE, MOTOR = 11, 1
FULL = MitLimits(2 * UNM_PER_NM, 10 * UNM_PER_NM)
"""2 N·m: 2·30 + 3/2·0.85·(2/0.945)² = 65.7 W."""


class Pair:
    """A supervisor service and a gate (or several: ``gates``, made at time 0 with the same
    timing), their frames carried through the codec."""

    def __init__(
        self,
        budget_uj: int,
        target_uj: int | None = None,
        hold_us: int = 20_000,
        gates: Callable[[Timing], list[MitGate]] | None = None,
    ) -> None:
        timing = Timing(response_timeout_us=20_000)
        config = DeviceConfig(limits=FULL, timing=timing, feedback_timeout_us=10**9)
        made = gates(timing) if gates else [MitGate(MOTOR, NODE, DM, config, 0, 7, hold_us=hold_us)]
        self.gates = {g.guard.node: g for g in made}
        self.gate = made[0]
        self.codec = Codec()
        self.service = build_service(
            Supervisor(tuple(self.gates), budget_uj, timing=timing),
            ServiceConfig(
                policy=TopUp(target_uj or budget_uj) if budget_uj else None,
                limits=GrantLimits(max_grant=max(target_uj or budget_uj, 1_000)),
                fsync=False,
                status_period_us=10**12,
                join_hold_us=0,
            ),
            0,
        )
        self.sent: list[bytes] = []
        self.sent_to: dict[int, list[bytes]] = {g.motor_id: [] for g in made}

    def route(self, up: list[Message], now: int) -> None:
        todo: deque[tuple[Direction, Message]] = deque((Direction.TO_SUPERVISOR, m) for m in up)
        while todo:
            direction, msg = todo.popleft()
            wire = self.codec.decode(*self.codec.encode(msg), direction=direction)
            if direction is Direction.TO_SUPERVISOR:
                down = self.service.on_message(wire, now)
                todo.extend((Direction.TO_CLIENT, m) for m in down)
            else:
                assert isinstance(wire, ToClient)
                gate = self.gates[wire.node]
                todo.extend((Direction.TO_SUPERVISOR, m) for m in gate.on_message(wire, now))

    now = 0

    def run_to(self, until: int, step: int = 1_000, reply: bool = True) -> None:
        t = self.now
        while t < until:
            t += step
            self.now = t
            up: list[Message] = []
            for gate in self.gates.values():
                if gate.next_wakeup() <= t:
                    up += gate.on_wakeup(t)
            wakeup = self.service.next_wakeup()
            if wakeup is not None and wakeup <= t:
                self.route(list(self.service.on_wakeup(t)), t)
            self.route(up, t)
            for gate in self.gates.values():
                self.deliver(gate, gate.take_frames(), t, reply)

    def deliver(self, gate: MitGate, frames: list[bytes], t: int, reply: bool = True) -> None:
        """``frames`` reach ``gate``'s motor, which answers each (at rest at 0, no torque)."""
        self.sent += frames
        self.sent_to[gate.motor_id] += frames
        answer = pack_reply(gate.model, gate.motor_id, 0x8000, 2048, 2048)
        for _ in frames if reply else ():
            self.route(gate.from_motor(answer, t, t), t)


def test_nothing_but_exit_reaches_the_motor_without_budget() -> None:
    pair = Pair(0)
    pair.run_to(50_000)
    assert pair.sent and set(pair.sent) == {EXIT}
    g = pair.gate
    assert g.from_app(ENTER, 50_000).frame is None
    assert g.from_app(encode(DM, 0, 0, 0, 0, 1.0).pack(), 50_000).frame is None
    assert g.from_app(EXIT, 50_000).frame == EXIT  # always: it makes the motor safer
    assert g.counts.refused == 2 and g.counts.forwarded == 1
    assert all(why.startswith("no budget") for why in g.counts.refused_why)


def test_with_budget_commands_pass_clamped_under_the_cap() -> None:
    pair = Pair(60_000_000, 5_000_000)
    pair.run_to(200_000)
    g = pair.gate
    assert g.guard.phase is GuardPhase.RUNNING and g.cap == FULL
    assert g.from_app(ENTER, pair.now).frame == ENTER
    small = encode(DM, 0.0, 0.0, 0.0, 0.02, 0.5)  # 0.02·30 + 0.5 = 1.1 N·m at worst
    assert g.from_app(small.pack(), pair.now).frame == small.pack()
    greedy = encode(DM, 12.5, 30.0, 500.0, 5.0, 10.0)
    v = g.from_app(greedy.pack(), pair.now)
    assert v.clamped and v.frame is not None
    sent = decode(DM, Command.unpack(v.frame))
    theta = decode(DM, Command(0x8000, 0, 0, 0, 0)).p
    horizon = g.hold_us + g.guard.reaction_us() + g.guard.latency_us()
    assert worst_torque(DM, sent, theta, 1_000, horizon) <= 2
    assert abs(sent.v) <= 10
    assert (g.counts.forwarded, g.counts.clamped, g.counts.refused) == (2, 1, 0)


def test_the_command_in_force_is_clamped_again_from_a_newer_reply() -> None:
    """A stiff command at the reply's position: once the motor is heard far off (replies stop
    moving the bound), the re-sent command carries less stiffness."""
    pair = Pair(60_000_000, 5_000_000)
    pair.run_to(200_000)
    g = pair.gate
    g.from_app(ENTER, pair.now)
    cmd = encode(DM, 0.0, 0.0, 20.0, 0.5, 0.0)
    first = decode(DM, Command.unpack(g.from_app(cmd.pack(), pair.now).frame or b""))
    far = pack_reply(DM, MOTOR, 0xF000, 2048, 2048)  # 10.9 rad away
    g.from_motor(far, pair.now, pair.now)
    pair.run_to(pair.now + g.hold_us + 1_000, reply=False)
    again = [f for f in pair.sent[-3:] if f not in (EXIT, ENTER)]
    assert g.counts.resent >= 1 and again
    assert decode(DM, Command.unpack(again[-1])).kp < first.kp


def test_the_budget_running_out_exits_motor_mode_and_refuses() -> None:
    pair = Pair(3_000_000)  # 3 J, 1 J of it the bound held back: 30 ms at 65.7 W
    g = pair.gate
    while g.guard.phase is not GuardPhase.RUNNING and pair.now < 500_000:
        pair.run_to(pair.now + 1_000)
    assert g.from_app(ENTER, pair.now).frame == ENTER
    g.from_app(encode(DM, 0.0, 0.0, 0.0, 0.0, 1.0).pack(), pair.now)
    pair.sent.clear()
    pair.run_to(pair.now + 200_000)
    assert g.guard.stop_reason == "budget exhausted" and not g.motor_mode
    assert g.guard.stops == 1 and g.guard.phase is GuardPhase.STOPPED
    assert EXIT in pair.sent
    assert g.from_app(encode(DM, 0.0, 0.0, 0.0, 0.0, 1.0).pack(), pair.now).frame is None
    assert g.guard.usable <= g.guard.threshold_uj()


def test_a_zeroed_origin_allows_no_stiffness_until_the_next_reply() -> None:
    pair = Pair(60_000_000, 5_000_000)
    pair.run_to(200_000)
    g = pair.gate
    g.from_app(ENTER, pair.now)
    assert g.from_app(ZERO, pair.now).frame == ZERO
    out = g.from_app(encode(DM, 1.0, 0.0, 5.0, 0.1, 0.0).pack(), pair.now).frame
    assert out is not None and decode(DM, Command.unpack(out)).kp == 0


def test_a_frame_from_someone_else_refuses_the_motor_for_good() -> None:
    pair = Pair(60_000_000, 5_000_000)
    pair.run_to(200_000)
    g = pair.gate
    pair.route(g.on_foreign(encode(DM, 0, 0, 500, 5, 10).pack(), pair.now), pair.now)
    pair.run_to(pair.now + 50_000)
    assert g.guard.refused is not None and "another sender" in g.guard.refused
    assert g.from_app(ENTER, pair.now).frame is None
    assert g.status(pair.now)["commands"]["foreign"] == 1
    assert Fraction(g.status(pair.now)["cap"]["torque_nm"]) == 0


def test_a_motor_still_showing_torque_after_its_stop_is_stuck() -> None:
    """Replies that show torque out of motor mode are a motor that did not obey exit."""
    pair = Pair(3_000_000)
    g = pair.gate
    while g.guard.phase is not GuardPhase.RUNNING and pair.now < 500_000:
        pair.run_to(pair.now + 1_000)
    g.from_app(ENTER, pair.now)
    g.from_app(encode(DM, 0.0, 0.0, 0.0, 0.0, 1.0).pack(), pair.now)
    while g.guard.stops == 0 and pair.now < 1_000_000:
        pair.run_to(pair.now + 1_000)
    pushing = pack_reply(DM, MOTOR, 0x8000, 2048, 2457)  # 2 N·m: it still pushes
    t = pair.now
    while t < pair.now + 700_000:
        t += 10_000
        pair.route(g.on_wakeup(t), t)
        pair.route(g.from_motor(pushing, t, t), t)
    assert g.guard.phase is GuardPhase.STUCK and g.guard.stuck is not None
    assert "still powered" in g.guard.stuck and g.counts.exits >= 5  # exit repeated


def test_a_stuck_motor_is_booked_uncontained_until_it_obeys_and_then_no_longer() -> None:
    """While STUCK the motor is charged, as uncontained, at its model's whole envelope (it holds
    its last command); once its replies show it powerless for a whole notice it is stopped, and
    nothing more is booked at that rate, neither uncontained nor metered."""
    whole = MitLimits(int(DM.t_max * UNM_PER_NM), int(DM.v_max * UNM_PER_NM))

    def made(timing: Timing) -> list[MitGate]:
        config = DeviceConfig(
            limits=FULL, timing=timing, feedback_timeout_us=10**9, stuck_limits=whole
        )
        return [MitGate(MOTOR, NODE, DM, config, 0, 7)]

    pair = Pair(3_000_000, gates=made)
    g = pair.gate
    while g.guard.phase is not GuardPhase.RUNNING and pair.now < 500_000:
        pair.run_to(pair.now + 1_000)
    g.from_app(ENTER, pair.now)
    g.from_app(encode(DM, 0.0, 0.0, 0.0, 0.0, 1.0).pack(), pair.now)
    while g.guard.stops == 0 and pair.now < 1_000_000:
        pair.run_to(pair.now + 1_000)
    pushing = pack_reply(DM, MOTOR, 0x8000, 2048, 2457)  # 2 N·m: it still pushes
    quiet = pack_reply(DM, MOTOR, 0x8000, 2048, 2048)  # no torque

    def step(reply: bytes) -> None:  # 1 ms on; the motor answers each frame the gate sent
        pair.now += 1_000
        if g.next_wakeup() <= pair.now:
            pair.route(g.on_wakeup(pair.now), pair.now)
        for _ in g.take_frames():
            pair.route(g.from_motor(reply, pair.now, pair.now), pair.now)

    while g.guard.phase is not GuardPhase.STUCK and pair.now < 3_000_000:
        step(pushing)
    assert g.guard.phase is GuardPhase.STUCK and g.counts.unasked == 0
    stuck_w = g.guard.profile.envelope(whole).fw / 1e15  # 442.77 W
    since = pair.now - g.guard.phase_at - g.guard.notice_us()
    assert g.guard.uncontained_uj >= stuck_w * since - 1  # from the stop's notice on
    notice = g.guard.notice_us()
    for _ in range(50):
        step(pushing)
    # the stop's time, long past, is no wake-up while STUCK: before, the gate took each pass as
    # a late one and raised the reaction (and the bound) 1 ms per ms
    assert g.guard.notice_us() == notice
    booked = g.guard.uncontained_uj + g.guard.metered_uj
    assert booked - g.guard.metered_uj >= stuck_w * (since + 50_000) - 1
    while g.guard.phase is GuardPhase.STUCK and pair.now < 4_000_000:
        step(quiet)  # it obeys at last
    assert g.guard.phase is GuardPhase.STOPPED and g.guard.stuck is None
    after = g.guard.uncontained_uj + g.guard.metered_uj
    # until it has shown itself powerless for a whole notice, and its next reply (a hold)
    assert after - booked <= stuck_w * (g.guard.notice_us() + 20_000) + 1
    for _ in range(200):
        step(quiet)
    assert g.guard.uncontained_uj + g.guard.metered_uj == after


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["none", "none", "command", "enter", "exit"]),
            st.builds(
                Command,
                st.one_of(st.integers(0x7F00, 0x8100), st.integers(0, 0xFFFF)),  # near θ too
                st.integers(0, 0xFFF),
                st.integers(0, 0xFFF),
                st.integers(0, 0xFFF),
                st.integers(0, 0xFFF),
            ),
            st.one_of(st.sampled_from([-30, 30]), st.integers(-30, 30)),
        ),
        min_size=20,
        max_size=120,
    )
)
def test_the_torque_in_force_never_exceeds_the_cap_whatever_the_motor_does(
    steps: list[tuple[str, Command, int]],
) -> None:
    """A motor that turns at any speed within the model's range, 1 ms at a time, answering every
    frame with its true position; the application sends anything. At every instant the command
    the motor holds asks for at most the cap, with the position and speed it really has."""
    pair = Pair(60_000_000, 5_000_000)
    g = pair.gate
    while g.guard.phase is not GuardPhase.RUNNING:
        pair.run_to(pair.now + 1_000)
    fp, fv = DM.fields()[0], DM.fields()[1]
    theta, in_force, enabled = Fraction(0), None, False
    cap = Fraction(g.cap.torque_unm, UNM_PER_NM)

    def deliver(frames: list[bytes], now: int) -> None:
        nonlocal in_force, enabled
        for data in frames:
            if data == ENTER:
                enabled = True
            elif data == EXIT:
                enabled, in_force = False, None
            elif data not in (ZERO,) and enabled:
                in_force = decode(DM, Command.unpack(data))
            code = round((theta + fp.span) * fp.top / (2 * fp.span))
            reply = pack_reply(DM, MOTOR, min(max(code, 0), fp.top), 2048, 2048)
            pair.route(g.from_motor(reply, now, now), now)

    for action, cmd, omega in steps:
        now = pair.now + 1_000
        pair.now = now
        theta += Fraction(omega, 1000)  # ω rad/s over 1 ms, |ω| <= 30 = Ω
        if action == "command":
            v = g.from_app(cmd.pack(), now)
            deliver([v.frame] if v.frame else [], now)
        elif action in ("enter", "exit"):
            v = g.from_app(ENTER if action == "enter" else EXIT, now)
            deliver([v.frame] if v.frame else [], now)
        pair.route(g.on_wakeup(now), now)
        deliver(g.take_frames(), now)
        if in_force is not None:
            for w in (Fraction(omega), fv.span, -fv.span):
                tau = in_force.kp * (in_force.p - theta) + in_force.kd * (in_force.v - w)
                assert abs(tau + in_force.t) <= cap, (tau + in_force.t, cap)


def test_a_reply_nobody_asked_for_refuses_the_motor() -> None:
    """Every frame is answered once: a reply beyond them is forged (e.g. a position next to
    the set point, to buy stiffness) or answers someone else's frame."""
    pair = Pair(60_000_000, 5_000_000)
    pair.run_to(200_000)  # every frame of the gate's answered
    g = pair.gate
    assert g.guard.refused is None
    forged = pack_reply(DM, MOTOR, 0x8000, 2048, 2048)
    pair.route(g.from_motor(forged, pair.now, pair.now), pair.now)
    assert g.guard.refused is not None and "no frame of the guard's asked for" in g.guard.refused
    assert g.counts.unasked == 1 and g.from_app(ENTER, pair.now).frame is None


def test_a_late_reply_is_late_not_forged() -> None:
    """A motor (or a host) stalled 300 ms: the answer comes after its frame counted as lost.
    It is taken as late, its round trip raises the latency the clamp allows, the motor runs on;
    one reply beyond every frame sent (lost ones included) still refuses it for good. (60 J
    covers what 2 N·m may draw over the longer notice; 5 J would not: the guard stops then.)"""
    pair = Pair(60_000_000)
    pair.run_to(200_000)
    g = pair.gate
    latency = g.guard.latency_us()
    pair.run_to(500_000, reply=False)  # the motor says nothing for 300 ms
    waiting = len(g.asked) + len(g.lost)
    assert waiting > 0
    reply = pack_reply(DM, MOTOR, 0x8000, 2048, 2048)
    for _ in range(waiting):
        pair.route(g.from_motor(reply, pair.now, pair.now), pair.now)
    assert g.guard.refused is None and g.counts.late > 0 and g.counts.unasked == 0
    assert g.guard.latency_us() >= REPLY_WINDOW_US > latency
    assert g.guard.phase is GuardPhase.RUNNING, g.guard.stop_reason
    pair.route(g.from_motor(reply, pair.now, pair.now), pair.now)
    assert g.guard.refused is not None and g.counts.unasked == 1


def test_a_reply_to_a_frame_lost_long_ago_is_forged() -> None:
    """Past ``LATE_WINDOW_US`` a lost frame's answer is no longer expected."""
    pair = Pair(60_000_000, 5_000_000, hold_us=10**7)  # the gate sends nothing more itself
    pair.run_to(200_000)
    g = pair.gate
    g.from_app(ENTER, pair.now)  # not answered
    at = pair.now + LATE_WINDOW_US + 1
    pair.route(g.from_motor(pack_reply(DM, MOTOR, 0x8000, 2048, 2048), at, at), at)
    assert g.guard.refused is not None and g.counts.late == 0 and g.counts.unasked == 1


def test_two_models_on_one_bus_are_each_clamped_by_their_own_ranges() -> None:
    """``canergy inline --mit 1,2 --mit-model 1:AK80-9,2:DM4310``: the gates its flags make, in
    explicit time, granted by one supervisor. The same burst of wire codes (the largest gains,
    velocity and feed-forward torque: 18 N·m to an AK80-9, 10 N·m to a DM4310) reaches each motor
    clamped so that, decoded by that motor's own ranges, it asks for at most the cap; clamped by
    the other model's ranges, what reaches the AK80-9 would ask for more."""
    argv = ["inline", "-i", "virtual", "-c", "motors"]
    argv += ["--app-interface", "virtual", "--app-channel", "app"]
    argv += ["--mit", "1,2", "--mit-nodes", "11,12", "--mit-model", "1:AK80-9,2:DM4310"]
    argv += ["--mit-resistance", "1:0.2", "--mit-max-torque", "2"]
    wanted = motors(build_parser().parse_args(argv))
    assert [(m.motor_id, m.model) for m in wanted] == [(1, "AK80-9"), (2, "DM4310")]

    def gates(timing: Timing) -> list[MitGate]:
        config = {"feedback_timeout_us": 10**9}
        return [gate_for(m, 0, timing, config) for m in wanted]

    pair = Pair(60_000_000, 30_000_000, gates=gates)  # 2 N·m: 101.8 W and 65.7 W
    while any(g.guard.phase is not GuardPhase.RUNNING for g in pair.gates.values()):
        assert pair.now < 1_000_000
        pair.run_to(pair.now + 1_000)
    push = Command(0x8000, 0x800, 0, 0, 0xFFF)  # the largest feed-forward torque alone
    burst = [push, Command(0xFFFF, 0xFFF, 0xFFF, 0xFFF, 0xFFF), Command(0, 0, 0xFFF, 0xFFF, 0)]
    for gate in pair.gates.values():
        pair.deliver(gate, [gate.from_app(ENTER, pair.now).frame or b""], pair.now)
    for k in range(40):
        for gate in pair.gates.values():
            v = gate.from_app(burst[k % 3].pack(), pair.now)
            assert v.frame is not None and v.clamped
            pair.deliver(gate, [v.frame], pair.now)
        pair.run_to(pair.now + 2_000)
    cap = Fraction(2)
    theta = Fraction(0)  # every reply: at rest at the middle of the range
    on_the_bench = {1: MODELS["AK80-9"], 2: DM}  # what each motor decodes its frames with
    for gate in pair.gates.values():
        model = on_the_bench[gate.motor_id]
        horizon = gate.hold_us + gate.guard.reaction_us() + gate.guard.latency_us()
        sent = pair.sent_to[gate.motor_id]
        commands = [Command.unpack(f) for f in sent if len(f) == 8 and f not in SPECIAL]
        assert len(commands) >= 40 and gate.counts.clamped == 40
        values = [decode(model, c) for c in commands]
        assert max(worst_torque(model, v, theta, 2_000, horizon) for v in values) <= cap
        assert max(v.t for v in values) > cap * Fraction(99, 100)  # tight, not timid
    as_dm = clamp(DM, push, pair.gates[11].cap, theta, 0, 0).command  # 2 N·m in ±10 N·m ...
    assert as_dm is not None and decode(MODELS["AK80-9"], as_dm).t > 3  # ... 3.6 in ±18 N·m


def test_a_budget_below_the_bound_holds_the_motor_and_says_so() -> None:
    """0.6 J granted where the cap's bound needs 0.985 J (65.7 W over 15 ms): the motor is kept
    out of motor mode, and the stop reason says what is held and needed, not "no budget yet";
    more budget releases it."""
    pair = Pair(600_000, 600_000)
    pair.run_to(200_000)
    g = pair.gate.guard
    assert g.phase is GuardPhase.STOPPED and 0 < g.usable < 600_000  # the set-up was charged
    assert g.stop_reason == (
        f"held: {g.usable / 1e6:.3f} J in hand, {g.threshold_uj() / 1e6:.3f} J needed to stop "
        "within the bound "
        "(raise the supervisor's --target and --max-grant, or lower the limits)"
    )
    assert g.threshold_uj() >= 985_000
    assert pair.gate.from_app(ENTER, 200_000).frame is None
    more = Pair(60_000_000, 5_000_000)
    more.run_to(200_000)
    assert more.gate.guard.phase is GuardPhase.RUNNING and more.gate.guard.stop_reason is None


def test_the_status_says_what_watchdog_the_motor_has() -> None:
    """CubeMars AK firmware has no watchdog; Damiao's CAN Timeout is not read without a policy
    that reads it (--mit-max-watchdog): both leave the motor unbounded after the gate's process
    died, and the status says so."""
    from canergy.live.devices.mit_motor import MitMotor

    ak = gate_for(MitMotor(1, 5, "AK80-9", resistance=0.2), 0, Timing()).status(0)["watchdog"]
    assert ak["state"] == "none" and ak["after_exit"] == "unbounded"
    assert ak["kind"] == "AK80-9: the firmware has no watchdog (a relay on its supply)"
    dm = gate_for(MitMotor(2, 6, "DM4310"), 0, Timing()).status(0)["watchdog"]
    assert dm["state"] == "not read" and dm["after_exit"] == "unbounded"
    assert dm["kind"] == "DM4310: the CAN Timeout register (RID 9)"
