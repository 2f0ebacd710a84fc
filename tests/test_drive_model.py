"""The emulated CiA 402 drive without CAN: virtual time, exact figures."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from canopen.profiles.p402 import State402
from hypothesis import given
from hypothesis import strategies as st
from support.drive_model import MS, NODE, enabled

from firmware_model.drive.model import SUBSTEP_US, DriveAbort, DriveModel
from firmware_model.drive.motor import LoadTorque, MotorParams
from firmware_model.drive.power import TORQUE_STATES

HOST = 1


def state_of(statusword: int) -> str:
    """The state python-canopen's BaseNode402 would read from ``statusword``."""
    for name, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return name
    return "UNKNOWN"


def test_starts_switch_on_disabled_and_statusword_matches_canopen() -> None:
    m = DriveModel(NODE)
    assert m.state == "NOT READY TO SWITCH ON"
    m.advance(SUBSTEP_US)
    assert m.state == "SWITCH ON DISABLED"
    for cw, state in [(0x06, "READY TO SWITCH ON"), (0x07, "SWITCHED ON")]:
        m.write(0x6040, 0, cw)
        assert state_of(m.read(0x6041)) == m.state == state
    m.write(0x6040, 0, 0x0F)
    assert state_of(m.read(0x6041)) == "OPERATION ENABLED"
    assert m.read(0x6041) & 0x0200  # remote
    m.write(0x6040, 0, 0x07)  # disable operation (5)
    assert m.state == "SWITCHED ON"
    m.write(0x6040, 0, 0x06)  # shutdown (6)
    assert m.state == "READY TO SWITCH ON"
    m.write(0x6040, 0, 0x0F)  # switch on + enable operation (3, 4)
    assert m.state == "OPERATION ENABLED"
    m.write(0x6040, 0, 0x00)  # disable voltage (9)
    assert m.state == "SWITCH ON DISABLED"
    assert m.read(0x1000) == 0x00020192 and m.read(0x6502) == 0x204


def test_pv_reaches_target_and_drawn_energy_is_the_integral_of_power() -> None:
    m = enabled({0x60FF: 80_000, 0x6083: 200_000})
    p = m.motor.params
    drawn = regenerated = friction = 0.0
    omega0 = m.velocity_rad_s
    t = MS
    while t < 800 * MS:  # ramp 0.4 s, then hold against the load
        w0 = m.velocity_rad_s
        t += SUBSTEP_US
        m.advance(t)
        w1, i = m.velocity_rad_s, m.motor.current
        dt = SUBSTEP_US / 1e6
        power = p.kt * i * (w0 + w1) / 2 + p.resistance * i * i
        drawn += max(power, 0.0) * dt
        regenerated += max(-power, 0.0) * dt
        friction += p.damping * (w0 * w0 + w0 * w1 + w1 * w1) / 3 * dt
    assert m.velocity_rad_s == pytest.approx(80.0, abs=0.05)
    assert m.read(0x606C) == pytest.approx(80_000, abs=50)
    assert m.read(0x6041) & 0x0400  # target reached
    assert m.drawn_uj == pytest.approx(drawn * 1e6, rel=1e-3)
    assert m.regenerated_uj == pytest.approx(regenerated * 1e6, rel=1e-3, abs=10)
    s = m.status()
    kinetic = 0.5 * p.inertia * (m.velocity_rad_s**2 - omega0**2)
    load = s["load_work_uj"] / 1e6
    balance = kinetic + friction + load + s["copper_loss_uj"] / 1e6
    assert (m.drawn_uj - m.regenerated_uj) / 1e6 == pytest.approx(balance, rel=1e-3)
    assert s["mechanical_work_uj"] / 1e6 == pytest.approx(kinetic + friction + load, rel=1e-3)
    assert m.peak_power_w >= max(0.0, p.kt * m.motor.current * m.velocity_rad_s)
    assert s["peak_power_w"] < 60  # 1.5 N·m limit x 80 rad/s plus copper at most


def test_energy_balance_holds_through_braking_and_regeneration() -> None:
    m = enabled({0x60FF: 150_000, 0x6083: 1_000_000, 0x6084: 2_000_000})
    m.advance(400 * MS)
    m.write(0x60FF, 0, -150_000)  # reverse hard: regenerates, then motors
    m.advance(900 * MS)
    m.write(0x6040, 0, 0x02)  # quick stop
    m.advance(1400 * MS)
    s, e = m.status(), m.motor.energy
    assert m.regenerated_uj > 0 and m.state == "SWITCH ON DISABLED"
    net = e.drawn.joules - e.regenerated.joules
    stored = m.motor.kinetic_j + e.friction.joules + e.load_work_j + e.copper_loss.joules
    assert net == pytest.approx(stored, rel=1e-6)
    assert s["drawn_uj"] == e.drawn.uj


def test_exact_energy_does_not_depend_on_how_time_is_chunked() -> None:
    a, b = enabled({0x60FF: 50_000}), enabled({0x60FF: 50_000})
    a.advance(300 * MS)
    for t in range(MS, 300 * MS + 1, 777):
        b.advance(t)
    b.advance(300 * MS)
    assert a.status() == b.status()


@pytest.mark.parametrize(
    ("option", "decel", "final"),
    [
        (1, 100.0, "SWITCH ON DISABLED"),
        (2, 400.0, "SWITCH ON DISABLED"),
        (5, 100.0, "QUICK STOP ACTIVE"),
        (6, 400.0, "QUICK STOP ACTIVE"),
    ],
)
def test_quick_stop_decelerates_at_the_configured_rate(
    option: int, decel: float, final: str
) -> None:
    m = enabled({0x60FF: 60_000, 0x6083: 600_000, 0x6084: 100_000, 0x6085: 400_000, 0x605A: option})
    m.advance(500 * MS)
    assert m.velocity_rad_s == pytest.approx(60.0, abs=0.05)
    m.write(0x6040, 0, 0x02)
    assert m.state == "QUICK STOP ACTIVE"
    m.advance(550 * MS)
    w1 = m.velocity_rad_s
    m.advance(590 * MS)
    w2 = m.velocity_rad_s
    assert (w1 - w2) / 0.04 == pytest.approx(decel, rel=0.05)
    m.advance(2 * 1_000_000)
    assert m.state == final
    assert abs(m.velocity_rad_s) < 0.05  # holding against a friction-like load: a small limit cycle
    assert m.status()["quick_stop_count"] == 1
    assert m.status()["stopped_at_us"] is not None
    if final == "QUICK STOP ACTIVE":
        assert m.read(0x6041) & 0x0400  # stopped
        m.write(0x6040, 0, 0x0F)  # 16: back to OPERATION ENABLED
        assert m.state == "OPERATION ENABLED"
    else:
        m.write(0x6040, 0, 0x0F)  # needs shutdown and switch on first
        assert m.state == "SWITCH ON DISABLED"


def test_quick_stop_option_0_coasts() -> None:
    m = enabled({0x60FF: 60_000, 0x6083: 600_000, 0x605A: 0})
    m.advance(500 * MS)
    m.write(0x6040, 0, 0x02)
    m.advance(600 * MS)
    assert m.state == "SWITCH ON DISABLED"
    assert m.motor.current == 0.0
    assert m.velocity_rad_s > 35.0  # only friction and the load slow it: about 200 rad/s²


def test_cst_torque_is_clipped_by_max_torque_and_max_current() -> None:
    m = enabled(mode=10)
    m.write(0x6071, 0, 200)
    m.advance(10 * MS)
    assert m.read(0x6077) == 200 and not m.read(0x6041) & 0x0800
    m.write(0x6071, 0, 2500)
    m.write(0x6072, 0, 1000)
    m.advance(20 * MS)
    assert m.read(0x6077) == 1000 and m.read(0x6078) == 1000
    assert m.read(0x6041) & 0x0800  # internal limit active
    m.write(0x6073, 0, 500)  # 2.5 A: 0.25 N·m
    m.advance(30 * MS)
    assert m.read(0x6077) == 500 and m.read(0x6078) == 500
    assert m.motor.torque == pytest.approx(0.25)
    assert m.read(0x2010) == round(m.motor.power_w / 24 * 1000)
    m.write(0x6071, 0, -300)
    m.advance(40 * MS)
    assert m.read(0x6077) == -300 and not m.read(0x6041) & 0x0800


def heartbeat_drive(option: int = 1) -> DriveModel:
    m = enabled({0x60FF: 30_000, 0x6007: option})
    m.write(0x1016, 1, HOST << 16 | 100)
    return m


def test_heartbeat_timeout_faults_then_fault_reset() -> None:
    m = heartbeat_drive()
    m.advance(500 * MS)
    assert m.state == "OPERATION ENABLED"  # consumer not active before the first heartbeat
    for t in range(500 * MS, 800 * MS, 50 * MS):
        m.host_heartbeat(HOST, t)
        m.host_heartbeat(HOST + 1, t + 70 * MS)  # another node's does not count
    last = 750 * MS
    m.advance(last + 100 * MS)
    assert m.state == "OPERATION ENABLED"
    m.advance(last + 100 * MS + 2 * SUBSTEP_US)
    assert m.state == "FAULT REACTION ACTIVE"
    assert m.read(0x603F) == 0x8130 and m.read(0x1001) & 1
    assert state_of(m.read(0x6041)) == "FAULT REACTION ACTIVE"
    assert m.take_emcys() == [(0x8130, m.read(0x1001))]
    m.advance(2 * 1_000_000)
    assert m.state == "FAULT" and abs(m.velocity_rad_s) < 0.01
    assert m.motor.current == 0.0
    s = m.status()
    assert (s["faults"], s["heartbeat_timeouts"]) == (1, 1)
    assert s["fault_reason"] == "heartbeat consumer timeout"
    assert [h["state"] for h in s["history"][-3:]] == [
        "OPERATION ENABLED",
        "FAULT REACTION ACTIVE",
        "FAULT",
    ]
    m.write(0x6040, 0, 0x0F)  # no rising edge of bit 7: stays
    assert m.state == "FAULT"
    m.write(0x6040, 0, 0x80)
    assert m.state == "SWITCH ON DISABLED" and m.read(0x603F) == 0
    assert m.take_emcys() == [(0, 0)]


@pytest.mark.parametrize(
    ("option", "state"),
    [(0, "OPERATION ENABLED"), (2, "SWITCH ON DISABLED"), (3, "QUICK STOP ACTIVE")],
)
def test_heartbeat_timeout_reaction_follows_6007(option: int, state: str) -> None:
    m = heartbeat_drive(option)
    m.host_heartbeat(HOST, 100 * MS)
    m.advance(200 * MS + 2 * SUBSTEP_US)
    assert m.state == state and m.status()["heartbeat_timeouts"] == 1
    assert m.faults == 0


def test_leaving_operational_while_enabled_is_a_communication_error() -> None:
    m = enabled({0x60FF: 30_000})
    m.set_nmt("OPERATIONAL", 2 * MS)
    m.set_nmt("PRE-OPERATIONAL", 100 * MS)
    assert m.state == "FAULT REACTION ACTIVE" and m.read(0x603F) == 0x8100
    m.advance(1_000_000)
    assert m.state == "FAULT"
    m.set_nmt("OPERATIONAL", 1_001_000)
    m.set_nmt("STOPPED", 1_002_000)  # not enabled: nothing more
    assert m.faults == 1


@given(st.lists(st.integers(0, 0xFFFF), max_size=40))
def test_any_controlword_sequence_is_harmless(words: list[int]) -> None:
    m = DriveModel(NODE)
    m.write(0x6060, 0, 3)
    m.write(0x60FF, 0, 20_000)
    t = MS
    for cw in words:
        m.write(0x6040, 0, cw, t)
        t += 3 * MS
        m.advance(t)
        assert state_of(m.read(0x6041)) == m.state
        if m.state not in TORQUE_STATES:
            assert m.motor.current == 0.0
        assert m.state not in ("FAULT", "FAULT REACTION ACTIVE")
    assert m.bad_writes == 0


def test_enable_operation_skipping_steps_does_nothing() -> None:
    m = DriveModel(NODE)
    m.advance(MS)
    for cw in (0x0F, 0x07, 0x1F, 0x8F):
        m.write(0x6040, 0, cw)
        assert m.state == "SWITCH ON DISABLED"
    m.write(0x6040, 0, 0x06)
    m.write(0x6040, 0, 0x02)  # quick stop from READY: 7
    assert m.state == "SWITCH ON DISABLED"


@pytest.mark.parametrize(
    ("index", "sub", "value", "code"),
    [
        (0x6041, 0, 0, 0x06010002),  # read-only
        (0x6060, 0, 1, 0x06090030),  # profile position: not supported
        (0x6060, 0, 200, 0x06090030),  # outside INTEGER8
        (0x6040, 0, -1, 0x06090030),
        (0x6085, 0, 0, 0x06090032),
        (0x605A, 0, 3, 0x06090030),
        (0x1234, 0, 0, 0x06020000),
        (0x1016, 7, 0, 0x06090011),
        (0x1A00, 1, 0x60400010, 0x08000022),  # mapping in use: sub 0 first
        (0x1A00, 0, 9, 0x06090030),
        (0x1800, 1, 0x190, 0x06090030),  # PDO valid: COB-ID cannot change
        (0x1800, 2, 250, 0x06090030),
    ],
)
def test_invalid_writes_are_refused_counted_and_change_nothing(
    index: int, sub: int, value: int, code: int
) -> None:
    m = enabled({0x60FF: 10_000})
    m.advance(50 * MS)
    before = (dict(m.values), m.state)
    with pytest.raises(DriveAbort) as info:
        m.write(index, sub, value)
    assert info.value.code == code
    assert m.bad_writes == 1
    assert (dict(m.values), m.state) == before


def test_remapping_a_tpdo_by_the_canopen_sequence() -> None:
    m = DriveModel(NODE)
    m.write(0x1801, 1, 0x8000_028A)  # invalid first
    m.write(0x1A01, 0, 0)
    with pytest.raises(DriveAbort):
        m.write(0x1A01, 1, 0x60850020)  # not mappable
    m.write(0x1A01, 1, 0x60780010)
    with pytest.raises(DriveAbort):
        m.write(0x1A01, 2, 0x60780020)  # wrong length
    m.write(0x1A01, 0, 1)
    m.write(0x1801, 1, 0x2A0)
    m.set_nmt("OPERATIONAL", MS)
    assert (0x2A0, b"\x00\x00") in m.due_tpdos(MS)


def test_tpdos_follow_event_timer_sync_and_nmt() -> None:
    m = DriveModel(NODE)
    assert m.due_tpdos(MS) == []  # PRE-OPERATIONAL
    m.set_nmt("OPERATIONAL", MS)
    sent = [f for t in range(MS, 101 * MS, MS) for f in m.due_tpdos(t)]
    ids = [cob for cob, _ in sent]
    assert (ids.count(0x18A), ids.count(0x28A), ids.count(0x38A)) == (10, 10, 10)
    sw, torque, energy = sent[0][1][0:2], sent[0][1][2:4], sent[0][1][4:8]
    assert int.from_bytes(sw, "little") == 0x240 and torque == b"\0\0" and energy == bytes(4)
    assert [len(dict(sent)[cob]) for cob in (0x18A, 0x28A, 0x38A)] == [8, 8, 8]
    m.set_nmt("PRE-OPERATIONAL", 101 * MS)
    m.write(0x1800, 2, 2)  # TPDO1 on every 2nd SYNC
    m.write(0x1801, 5, 0)  # TPDO2 on change only
    m.set_nmt("OPERATIONAL", 102 * MS)
    frames = [f for t in range(102 * MS, 200 * MS, MS) for f in m.due_tpdos(t)]
    assert [cob for cob, _ in frames].count(0x28A) == 1  # nothing changed after the first
    synced = [f for t in range(10) for f in m.receive(0x80, b"", 200 * MS + t * MS)]
    assert [cob for cob, _ in synced] == [0x18A] * 5
    m.receive(0x20A, b"\x06\x00", 300 * MS)  # RPDO1 controlword: shutdown
    assert m.state == "READY TO SWITCH ON"
    m.receive(0x20A, b"\x07", 301 * MS)  # too short
    assert m.decode_errors == 1 and m.state == "READY TO SWITCH ON"


def test_load_profile_and_opposing_load(tmp_path: Path) -> None:
    path = tmp_path / "load.csv"
    path.write_text("time_s,newton_metres\n0,0.1\n0.5,-0.2\n")
    load = LoadTorque.from_csv(path, opposing=True)
    assert load.at(0.2, 3.0) == 0.1 and load.at(0.7, 3.0) == 0.2 and load.at(0.7, -1.0) == -0.2
    assert load.at(0.7, 0.0) == 0.0
    assert LoadTorque.from_csv(path).at(0.7, 1.0) == -0.2
    path.write_text("0,1\n0,2\n")
    with pytest.raises(ValueError, match="increase"):
        LoadTorque.from_csv(path)


def test_rated_values_follow_motor_params() -> None:
    m = DriveModel(NODE, params=MotorParams(kt=0.05, rated_current=2.0, dc_voltage=48.0))
    assert (m.read(0x6075), m.read(0x6076), m.read(0x6079)) == (2000, 100, 48000)


# -- 0x2011 energy drawn ---------------------------------------------------------------------


def test_energy_drawn_object_is_drawn_uj_modulo_2_32_and_in_tpdo1() -> None:
    m = enabled({0x60FF: 50_000})
    m.set_nmt("OPERATIONAL", MS)
    m.advance(200 * MS)
    assert m.drawn_uj > 0 and m.read(0x2011) == m.drawn_uj
    frame = dict(m.due_tpdos(200 * MS))[0x18A]
    assert int.from_bytes(frame[4:8], "little") == m.drawn_uj
    m.motor.energy.drawn.uj = 2**32 + 7
    assert m.read(0x2011) == 7
    with pytest.raises(DriveAbort):
        m.write(0x2011, 0, 0)  # read-only


# -- limits: 0x6072, 0x6073, 0x6080 and the power envelope -----------------------------------


def envelope(m: DriveModel) -> tuple[float, float, float]:
    """``(τ_max N·m, i_max A, P_max W)`` from the limit objects now in force."""
    p = m.motor.params
    tau_max = min(
        m.read(0x6072) / 1000 * p.rated_torque,
        m.read(0x6073) / 1000 * p.rated_current * p.kt,
    )
    i_max = tau_max / p.kt
    return tau_max, i_max, tau_max * m.read(0x6080) / 1000 + p.resistance * i_max**2


def within(value: float, bound: float) -> bool:
    """``value <= bound`` but for float rounding."""
    return value <= bound * (1 + 1e-9) + 1e-12


@dataclass
class Trace:
    """Per substep: the envelope in force (W) and the exact energy drawn at its end (J)."""

    envelope_w: list[float]
    drawn_j: list[float]


def run_checked(m: DriveModel, substeps: int, events: dict[int, list[Event]]) -> Trace:
    """Run ``substeps`` substeps, applying ``events`` before theirs; check every substep's
    torque, current and power (at both ends: P is monotonic within one) against the limits."""
    p, trace = m.motor.params, Trace([], [m.motor.energy.drawn.joules])
    for k in range(substeps):
        for event in events.get(k, []):
            event(m)
        tau_max, i_max, p_max = envelope(m)
        w0 = m.motor.omega
        m.advance(m.time_us + SUBSTEP_US)
        tau, i, w1 = m.motor.torque, m.motor.current, m.motor.omega
        assert within(abs(tau), tau_max) and within(abs(i), i_max), (k, tau, i)
        for w in (w0, w1):
            assert within(tau * w + p.resistance * i * i, p_max), (k, tau, w, p_max)
        trace.envelope_w.append(p_max)
        trace.drawn_j.append(m.motor.energy.drawn.joules)
    return trace


def check_windows(trace: Trace, lengths: tuple[int, ...] = (1, 7, 100, 10**9)) -> None:
    """Energy drawn over any window of these lengths is within the envelope's integral."""
    dt = SUBSTEP_US / 1e6
    allowed = [0.0]
    for p_max in trace.envelope_w:
        allowed.append(allowed[-1] + p_max * dt)
    n = len(trace.envelope_w)
    for length in (min(w, n) for w in lengths):
        for a in range(n - length + 1):
            drawn = trace.drawn_j[a + length] - trace.drawn_j[a]
            assert within(drawn, allowed[a + length] - allowed[a]), (a, length, drawn)


Event = Callable[[DriveModel], None]


def write(index: int, value: int) -> Event:
    def event(m: DriveModel) -> None:
        m.write(index, 0, value)

    return event


def fault(m: DriveModel) -> None:
    m.fault("injected", 0x5000)


_EVENTS: st.SearchStrategy[Event] = st.one_of(
    st.builds(write, st.just(0x60FF), st.integers(-300_000, 300_000)),
    st.builds(write, st.just(0x6071), st.integers(-3000, 3000)),
    st.builds(write, st.sampled_from([0x6072, 0x6073]), st.integers(0, 3000)),
    st.builds(write, st.just(0x6080), st.integers(1, 200_000)),
    st.builds(write, st.just(0x6060), st.sampled_from([3, 10])),
    st.builds(write, st.just(0x6040), st.sampled_from([0x02, 0x06, 0x07, 0x0F, 0x00, 0x80])),
    st.builds(write, st.just(0x605A), st.sampled_from([0, 1, 2, 5, 6])),
    st.just(fault),
)


@st.composite
def loads(draw: st.DrawFn) -> LoadTorque:
    """Constant or stepped loads, either sign (overhauling when they push the motor along)."""
    torques = draw(st.lists(st.floats(-0.5, 0.5), min_size=1, max_size=4))
    rows = tuple((0.05 * k, nm) for k, nm in enumerate(torques))
    return LoadTorque(rows, opposing=draw(st.booleans()))


@given(
    loads(),
    st.sampled_from([3, 10]),
    st.dictionaries(
        st.sampled_from([0x60FF, 0x6071, 0x6072, 0x6073, 0x6080, 0x6083]),
        st.integers(1, 3000),
        max_size=6,
    ),
    st.lists(st.tuples(st.integers(0, 1999), _EVENTS), max_size=25),
)
def test_power_never_exceeds_the_limits_envelope(
    load: LoadTorque,
    mode: int,
    initial: dict[int, int],
    events: list[tuple[int, Event]],
) -> None:
    """Whatever the profile, the load and the limits (changed at any substep), the electrical
    power drawn stays within τ_max·ω_max + R·i_max² at every instant, and so does the energy
    drawn over any window."""
    m = DriveModel(NODE, load=load)
    m.advance(MS)
    m.write(0x6060, 0, mode)
    for index, value in initial.items():
        scale = 100 if index in (0x60FF, 0x6080, 0x6083) else 1  # velocities up to 300 rad/s
        m.write(index, 0, value * scale)
    for cw in (0x06, 0x07, 0x0F):
        m.write(0x6040, 0, cw)
    by_substep: dict[int, list[Event]] = {}
    for k, event in events:
        by_substep.setdefault(k, []).append(event)
    check_windows(run_checked(m, 2000, by_substep))


def test_max_speed_holds_against_an_overhauling_load_in_cst() -> None:
    """The load pushes the rotor along past 0x6080: the drive gives no motoring torque."""
    m = DriveModel(NODE, load=LoadTorque.constant(-0.3))
    m.advance(MS)
    for index, value in ((0x6060, 10), (0x6080, 20_000), (0x6071, 1000)):
        m.write(index, 0, value)
    for cw in (0x06, 0x07, 0x0F):
        m.write(0x6040, 0, cw)
    past = 0
    for _ in range(3000):
        w0 = m.velocity_rad_s
        m.advance(m.time_us + SUBSTEP_US)
        if w0 > 20.0:
            past += 1
            assert m.motor.torque <= 0.0 and m.read(0x6041) & 0x0800
        assert m.motor.torque * max(w0, m.velocity_rad_s) <= 0.5 * 20.0 * (1 + 1e-9)
    assert past > 1000 and m.velocity_rad_s > 100  # the load alone drives it, unhelped


def test_pv_target_is_clamped_to_max_speed() -> None:
    m = enabled({0x60FF: 100_000, 0x6083: 1_000_000, 0x6080: 30_000})
    trace = run_checked(m, 5000, {})
    assert m.velocity_rad_s == pytest.approx(30.0, abs=0.05) and m.velocity_rad_s <= 30.0 + 1e-9
    assert m.read(0x6041) & 0x0400  # the clamped target is reached
    check_windows(trace)
    m.write(0x6080, 0, 10_000)  # lowered while faster: the drive slows down to it
    run_checked(m, 5000, {})
    assert m.velocity_rad_s == pytest.approx(10.0, abs=0.05)
    m.write(0x60FF, 0, -100_000)
    run_checked(m, 5000, {})
    assert m.velocity_rad_s == pytest.approx(-10.0, abs=0.05)


def test_max_speed_is_refused_at_0_and_leaves_the_defaults_alone() -> None:
    m = DriveModel(NODE)
    assert m.read(0x6080) == 10_000_000  # 10,000 rad/s
    with pytest.raises(DriveAbort) as info:
        m.write(0x6080, 0, 0)
    assert info.value.code == 0x06090032 and m.read(0x6080) == 10_000_000


@pytest.mark.parametrize("index", [0x6072, 0x6073])
@pytest.mark.parametrize("then", ["running", "quick stop", "fault"])
def test_zero_max_torque_or_current_means_no_torque_in_every_state(index: int, then: str) -> None:
    m = enabled({0x60FF: 60_000, 0x6083: 600_000, 0x605A: 6})
    m.advance(300 * MS)
    assert m.velocity_rad_s > 50
    m.write(index, 0, 0)
    if then == "quick stop":
        m.write(0x6040, 0, 0x02)
    elif then == "fault":
        m.fault("injected", 0x5000)
    for _ in range(2000):
        m.advance(m.time_us + SUBSTEP_US)
        assert m.motor.current == 0.0 and m.motor.torque == 0.0
    assert m.state in TORQUE_STATES or m.state == "FAULT"
    assert m.drawn_uj == m.status()["drawn_uj"]
