"""``canergy.cia402.watch``: frames to a guarded drive decoded into writes, sans-IO; and the guard
answering them (charge at the reach, read-back, latch) without a bus."""

from __future__ import annotations

from fractions import Fraction

from canergy.cia402.envelope import Limits, Ratings, StopKind
from canergy.cia402.guard import CW_DISABLE_VOLTAGE, Command, DriveGuard, GuardConfig, VerifyCommand
from canergy.cia402.meter import MeterConfig, MeterKind
from canergy.cia402.metering import DriveSetup
from canergy.cia402.watch import SdoWatch, Watched, Write, check, nmt_writes, pdo_writes


def download(index: int, sub: int, value: int, size: int = 4) -> bytes:
    """An expedited SDO download request with its size."""
    first = 0x23 | (4 - size) << 2
    return bytes([first, index & 0xFF, index >> 8, sub]) + value.to_bytes(4, "little")


def test_an_expedited_download_is_a_write_with_its_value() -> None:
    w = SdoWatch()
    assert w.frame(download(0x6072, 0, 3000, 2)) == [Write(0x6072, 0, 3000)]
    assert w.frame(bytes([0x40, 0x72, 0x60, 0, 0, 0, 0, 0])) == []  # an upload: a read
    assert w.frame(bytes([0x80, 0x72, 0x60, 0, 0, 0, 0, 0])) == []  # an abort


def test_every_frame_of_a_segmented_download_counts_until_its_last() -> None:
    w = SdoWatch()
    start = bytes([0x21, 0x00, 0x1A, 1, 8, 0, 0, 0])  # 8 bytes to 0x1A00:1, segmented
    segment = bytes([0x00, 1, 2, 3, 4, 5, 6, 7])
    last = bytes([0x1D, 8, 0, 0, 0, 0, 0, 0])  # toggle 1, 1 byte, last
    assert w.frame(start) == [Write(0x1A00, 1, None, "SDO segmented")]
    assert w.frame(segment) == [Write(0x1A00, 1, None, "SDO segmented")]
    assert w.frame(last) == [Write(0x1A00, 1, None, "SDO segmented")]
    assert w.frame(bytes([0x40, 0x41, 0x60, 0, 0, 0, 0, 0])) == []  # closed: a read again


def test_a_block_download_counts_to_its_end_whatever_its_segments_look_like() -> None:
    w = SdoWatch()
    start = bytes([0xC6, 0x80, 0x60, 0, 4, 0, 0, 0])  # block download to 0x6080
    looks_like_a_read = bytes([0x41, 0x72, 0x60, 0, 0, 0, 0, 0])  # sequence 65, not a read
    end = bytes([0xC1 | 3 << 2, 0, 0, 0, 0, 0, 0, 0])
    for frame in (start, looks_like_a_read, end):
        assert w.frame(frame) == [Write(0x6080, 0, None, "SDO block")]
    assert w.frame(looks_like_a_read) == []


def test_a_segment_whose_start_was_not_seen_is_an_unknown_write() -> None:
    assert SdoWatch().frame(bytes([0x00, 1, 2, 3, 4, 5, 6, 7])) == [
        Write(None, 0, None, "SDO segment")
    ]


def test_nmt_commands_other_than_start_to_the_drive_or_to_all_are_unknown_writes() -> None:
    assert nmt_writes(bytes([0x81, 10]), 10) == [Write(None, 0, 0x81, "NMT")]
    assert nmt_writes(bytes([0x82, 0]), 10) == [Write(None, 0, 0x82, "NMT")]
    assert nmt_writes(bytes([0x81, 11]), 10) == []
    assert nmt_writes(bytes([0x01, 10]), 10) == []


def test_an_rpdo_is_decoded_by_its_map() -> None:
    mapping = ((0x6040, 0, 16), (0x6060, 0, 8))
    assert pdo_writes(bytes([0x0F, 0x00, 0x03]), mapping) == [
        Write(0x6040, 0, 15, "RPDO"),
        Write(0x6060, 0, 3, "RPDO"),
    ]
    assert pdo_writes(bytes([0x0F]), mapping) == []  # too short for its map: nothing decoded


def test_what_the_bound_depends_on() -> None:
    disable = Watched(StopKind.DISABLE, counter=(0x2011, 0))
    for index in (0x1400, 0x1A00, 0x1BFF, 0x6072, 0x6073, 0x6080, 0x6076, 0x6060, 0x1016, 0x2011):
        assert disable.matters(Write(index)), hex(index)
    assert disable.matters(Write(None))
    for index in (0x60FF, 0x6083, 0x6085, 0x1C00, 0x6040):
        assert not disable.matters(Write(index)), hex(index)
    assert Watched(StopKind.QUICK).matters(Write(0x6085))


def test_a_read_back_names_what_differs_and_lets_the_stop_ramps_rise() -> None:
    setup = {(0x1A00, 3): 0x2011_0020, (0x6085, 0): 500_000, (0x6084, 0): 100_000}
    limits = Limits(265, 265, 100_500)
    read: dict[tuple[int, int], int | None] = {
        (0x1A00, 3): 0x2011_0020,
        (0x6085, 0): 600_000,
        (0x6084, 0): 10_000_000,  # steeper: a faster stop
        (0x6072, 0): 265,
        (0x6073, 0): 265,
        (0x6080, 0): 100_500,
    }
    assert check(setup, read, limits) is None
    read[0x6085, 0] = 1_000
    read[0x6072, 0] = 3000
    assert check(setup, read, limits) == (
        "0x6072:0 = 3000 (expected 265); 0x6085:0 = 1000 (expected 500000)"
    )


RATINGS = Ratings(500, 5000, Fraction(1, 1000), 1000)
FULL = Limits(265, 265, 100_500)
REACH = Limits(3000, 3000, 150_000)


def guard(kind: MeterKind = MeterKind.ENVELOPE) -> DriveGuard:
    g = DriveGuard(10, GuardConfig(MeterConfig(kind), FULL, stop=StopKind.DISABLE), 0, 1)
    g.on_ready(0, DriveSetup(RATINGS, 0, 0, FULL.closed(), REACH, {(0x1A00, 3): 0x2011_0020}))
    g.commands.clear()
    return g


def verifies(g: DriveGuard) -> list[VerifyCommand]:
    return [c for c in g.commands if isinstance(c, VerifyCommand)]


def test_a_limit_written_while_the_drive_may_run_is_charged_at_the_reach_until_read_back() -> None:
    g = guard()
    g.phase = g.phase.RUNNING  # as a grant would leave it
    g.metering.confirm(0, FULL)
    g.state = "OPERATION ENABLED"
    g.on_write(1_000, Write(0x6072, 0, 3000), age_us=200)
    assert g.metering.suspect_from == 800  # from when it was on the bus
    (ask,) = verifies(g)
    assert ask.seq == g.seq and all(k[0] != 0x1A00 for k in ask.keys)  # its scope only
    before = g.metering.metered_uj
    g.on_wakeup(11_000)
    reach_w = RATINGS.envelope_fw(REACH) / 1e15
    assert g.metering.metered_uj - before >= reach_w * 0.01 * 1e6 * 0.99  # 10 ms at the reach
    read = {(0x6041, 0): 0x0627, (0x6072, 0): 3000, (0x6073, 0): 265, (0x6080, 0): 100_500}
    g.on_verified(12_000, ask.seq, dict(read))
    assert g.latched and g.refused is not None and "0x6072:0 = 3000 (expected 265)" in g.refused
    assert [c.controlword for c in g.commands if isinstance(c, Command)] == [CW_DISABLE_VOLTAGE]


def test_a_limit_written_long_before_it_is_taken_in_is_metered_at_the_reach_at_once() -> None:
    """Taken in 80 ms after it was on the bus: those 80 ms at the reach are metered and booked
    in that same call, not left in the clock's remainder until the clock next runs (a host
    that exits first never meters them)."""
    g = guard()
    g.phase = g.phase.RUNNING
    g.metering.confirm(0, FULL)
    g.on_wakeup(20_000)
    before = g.metering.metered_uj
    g.on_write(100_000, Write(0x6072, 0, 3000), age_us=80_000)
    charged_fw = max(RATINGS.envelope_fw(FULL), RATINGS.envelope_fw(FULL.closed()))
    lacking = (RATINGS.envelope_fw(REACH) - charged_fw) * 80_000 // 10**15
    assert lacking > 0
    assert g.metering.metered_uj - before >= lacking
    assert g.metering.clock.remainder < 10**15
    assert g.client.state.spent + g.debt_uj == g.metering.metered_uj  # booked


def test_an_enabling_controlword_to_a_drive_held_stopped_is_answered_at_once() -> None:
    """By SDO, whatever carries the controlword otherwise; charged at the reach only while a
    write to the configuration is not read back yet (else the limits it holds bound it)."""
    g = guard()
    g.state = "SWITCH ON DISABLED"
    g.on_write(5_000, Write(0x6040, 0, 0x0F), 0)
    stops = [c for c in g.commands if isinstance(c, Command)]
    assert [(c.controlword, c.at, c.by_sdo) for c in stops] == [(CW_DISABLE_VOLTAGE, 5_000, True)]
    assert g.restops == 1 and g.metering.suspect_from is None and not verifies(g)
    g.on_write(6_000, Write(0x6072, 0, 3000), 0)  # held off: read back, not charged
    assert g.metering.suspect_from is None
    g.on_write(7_000, Write(0x6040, 0, 0x0F), 0)
    assert g.restops == 2 and g.metering.suspect_from == 7_000
    (ask,) = verifies(g)
    g.on_verified(8_000, ask.seq, {(0x6041, 0): 0x0640, **{(i, 0): 0 for i in (0x6072, 0x6073)}})
    assert g.metering.suspect_from is not None and not g.latched  # 0x6080 unread: again
    closed = {(0x6072, 0): 0, (0x6073, 0): 0, (0x6080, 0): 100_500}
    g.on_verified(9_000, g.seq, {(0x6041, 0): 0x0640, **closed})
    assert g.metering.suspect_from is None and g.suspect is None and not g.latched


def test_a_write_that_cannot_be_read_back_in_time_stops_the_drive_for_good() -> None:
    g = guard()
    g.phase = g.phase.RUNNING
    g.on_write(0, Write(0x1A00, 3, 0x6084_0020), 0)
    g.on_wakeup(g.config.pdo_timeout_us + 1)
    assert g.latched and g.refused is not None and "not verified in time" in g.refused


def test_a_periodic_read_back_asked_before_the_guards_own_write_is_judged_as_asked() -> None:
    """The read-back asked at 1 s reads the closed limits; the guard's own full limits, written
    and read back meanwhile, are taken in first (the host drains limits answers before
    read-backs): what the read-back shows was in force when it was asked, no change behind the
    guard. A value nobody wrote still stops the drive for good."""
    config = GuardConfig(MeterConfig(MeterKind.ENVELOPE), FULL, pdo_timeout_us=10_000_000)
    for closed_read, refused in ((FULL.closed(), False), (Limits(3000, 0, 0), True)):
        g = DriveGuard(10, config, 0, 1)  # TPDOs may pause 10 s: none here
        g.on_ready(0, DriveSetup(RATINGS, 0, 0, FULL.closed(), REACH, {(0x1A00, 3): 0x2011_0020}))
        g.metering.confirm(0, FULL.closed())
        g.on_wakeup(1_000_000)
        (ask,) = verifies(g)
        assert ask.why == "periodic read-back"
        g.phase = g.phase.RUNNING  # as a grant would leave it: the full limits written
        g.metering.write(1_005_000, FULL)
        g.metering.confirm(1_010_000, FULL)  # and read back, taken in before the read-back
        read = {(0x6041, 0): 0x0640, (0x6072, 0): closed_read.torque_permille}
        read |= {(0x6073, 0): closed_read.current_permille, (0x6080, 0): closed_read.speed}
        read |= {(0x1A00, 3): 0x2011_0020}
        g.on_verified(1_020_000, ask.seq, read)
        assert (g.refused is not None) is refused, g.refused
        assert g.latched is refused


def test_the_exit_charges_a_quick_stop_under_way_at_the_bounds_stop_part() -> None:
    """The host exits while the drive's quick stop runs: past the last reading, charged up to
    the latency and what the stop may draw (no reading will show the ramp); a stop that
    disabled the drive is charged no stop part."""
    for stop in StopKind.QUICK, StopKind.DISABLE:
        g = DriveGuard(10, GuardConfig(MeterConfig(MeterKind.ENVELOPE), FULL, stop=stop), 0, 1)
        g.on_ready(0, DriveSetup(RATINGS, 0, 0, FULL.closed(), REACH, {}))
        g.phase = g.phase.RUNNING  # as a grant would leave it
        g.metering.confirm(0, FULL)
        g.state = "OPERATION ENABLED"
        g.on_wakeup(1_000)
        g.halt(1_000)
        before = g.metering.metered_uj
        g.on_exit(2_000)
        charged = g.metering.metered_uj - before
        bound = g.metering.bound(FULL)
        assert bound is not None
        latency = g.metering.timings().latency_us
        clock = RATINGS.envelope_fw(FULL) * (1_000 + latency) // 10**15
        if stop is StopKind.QUICK:
            assert g.phase is g.phase.STOPPING and bound.stop_uj > clock
            assert charged >= clock + bound.stop_uj
        else:
            assert g.phase is g.phase.STOPPED and bound.stop_uj == 0
            assert clock <= charged <= clock + 1
        assert g.client.state.spent + g.debt_uj == g.metering.metered_uj  # booked
