"""The emulated CiA 402 drive without CAN: virtual time, exact figures."""

from __future__ import annotations

from pathlib import Path

import pytest
from canopen.profiles.p402 import State402
from hypothesis import given
from hypothesis import strategies as st

from firmware_model.drive.model import SUBSTEP_US, DriveAbort, DriveModel
from firmware_model.drive.motor import LoadTorque, MotorParams
from firmware_model.drive.power import TORQUE_STATES

NODE, HOST = 10, 1
MS = 1000


def state_of(statusword: int) -> str:
    """The state python-canopen's BaseNode402 would read from ``statusword``."""
    for name, (mask, bits) in State402.SW_MASK.items():
        if statusword & mask == bits:
            return name
    return "UNKNOWN"


def enabled(objects: dict[int, int] | None = None, mode: int = 3) -> DriveModel:
    """A drive in OPERATION ENABLED at t = 1 ms in ``mode``, with ``objects`` written first."""
    m = DriveModel(NODE, load=LoadTorque.constant(0.02, opposing=True))
    m.advance(MS)
    m.write(0x6060, 0, mode)
    for index, value in (objects or {}).items():
        m.write(index, 0, value)
    for cw in (0x06, 0x07, 0x0F):
        m.write(0x6040, 0, cw)
    assert m.state == "OPERATION ENABLED"
    return m


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
    sw, torque, mode = sent[0][1][0:2], sent[0][1][2:4], sent[0][1][4:5]
    assert int.from_bytes(sw, "little") == 0x240 and torque == b"\0\0" and mode == b"\0"
    assert len(dict(sent)[0x28A]) == 8 and len(dict(sent)[0x38A]) == 8
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
