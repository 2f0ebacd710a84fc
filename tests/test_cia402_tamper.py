"""Issue 40, items 1-4: what the application writes behind the guard, on python-can's virtual bus.

``canergy supervisor --cia402`` (its real ``main``) guards the emulated drive; an independent
python-canopen master (the application) writes by SDO what the guard's bound depends on: the
limits, the controlword of a drive the guard stopped, the TPDO map that carries the counter, the
quick stop deceleration. The drive must draw at most what it was granted plus the bound the guard
states for a write it sees (at the drive's reach: ``--cia402-reach-*``), however long the
application goes on, and a configuration the guard cannot verify stops the drive for good.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import canopen
import pytest

from canergy.devices.proxy import HELD
from canergy.live.canopen.cia402_link import shared_sdo
from firmware_model.drive.live_bench import DRIVE, Bench, app_write, guarded_bench, wait_for

REACH = ("--cia402-reach-torque", "3000", "--cia402-reach-current", "3000")
REACH_SPEED = 150_000
"""What the application opens the limits to: the drive's own maxima, given to the guard."""
REACH_FLAGS = (*REACH, "--cia402-reach-speed", str(REACH_SPEED))
LIMITS = (0x6072, 0x6073, 0x6080)
ATTACK_S = 4.0
GAP_MS = 400
"""The PDO timeout: the bound at the reach is 450 W over it, a reaction and a latency (187-286 J
measured; with no watch the drive drew 291 J on 9 J granted opening the limits). A late TPDO
stops the drive for good: at 50 ms one did before it was first enabled (5 of 12 runs beside 4
busy loops, worst gaps 200-243 ms there)."""
SHORT_GAP_MS = 50
"""Where a late TPDO's stop does no harm (the drive stopped is where the test begins): the 3 J
budget outlasts the 400 ms gap's bound, and the guard tapered the limits so far that the drive
still held 1.35 J after 60 s."""


def books(final: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    granted = final["nodes"][str(DRIVE)]
    drive = final["cia402"]["drives"][str(DRIVE)]
    return granted["delivered_uj"] - granted["returns_credited_uj"], drive


def open_limits(app: canopen.RemoteNode, segmented: bool = False) -> None:
    """3000 ‰ and the reach's speed, by expedited SDO or (``segmented``) segmented SDO."""
    for index, value, size in ((0x6072, 3000, 2), (0x6073, 3000, 2), (0x6080, REACH_SPEED, 4)):
        if not segmented:
            app_write(app, index, value)
            continue

        for _ in range(10):  # the guard's reads interleave with it on the one SDO server
            with contextlib.suppress(canopen.SdoCommunicationError, canopen.SdoAbortedError):
                app.sdo.download(index, 0, value.to_bytes(size, "little"), force_segment=True)
                break
            time.sleep(0.01)


def swing(
    b: Bench, until: float, each: Callable[[], None] | None = None, brake: bool = True
) -> None:
    """Target velocity ±150 rad/s every 50 ms, speeding up at 20,000 rad/s² (as hard as the limits
    let it) and braking as hard unless not ``brake``, ``each`` between swings, until ``until``
    (monotonic s)."""
    app_write(b.app, 0x6083, 20_000_000)
    if brake:
        app_write(b.app, 0x6084, 20_000_000)
    sign = 1
    while time.monotonic() < until:
        app_write(b.app, 0x60FF, sign * REACH_SPEED)
        sign = -sign
        if each is not None:
            each()
        time.sleep(0.05)


def assert_inside_reach_bound(b: Bench, final: dict[str, Any]) -> dict[str, Any]:
    granted, drive = books(final)
    drawn = b.drawn()
    print(f"drawn {drawn / 1e6:.3f} J, granted {granted / 1e6:.3f} J, drive {drive}")
    assert drive["bound_reach_uj"] is not None
    assert drawn <= granted + drive["bound_reach_uj"]
    return drive


@pytest.mark.parametrize(
    ("mode", "segmented"), [("envelope", False), ("counter", False), ("envelope", True)]
)
def test_limits_opened_by_the_application_stop_the_drive(
    tmp_path: Path, mode: str, segmented: bool
) -> None:
    """Item 2: 0x6072/0x6073 = 3000 ‰ and 0x6080 raised while the drive runs, the application
    swinging the motor as hard as they let it: the write is charged at the drive's reach, the
    read-back differs from what the guard wrote, the drive is stopped and kept stopped."""
    with guarded_bench(
        tmp_path,
        10,
        "--initial",
        "100J",
        "--target",
        "2J",
        *REACH_FLAGS,
        with_node=False,
        mode=mode,
        gap_ms=GAP_MS,
    ) as b:
        wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
        swing(b, time.monotonic() + ATTACK_S, lambda: open_limits(b.app, segmented))
        final = b.stop()
    drive = assert_inside_reach_bound(b, final)
    assert drive["latched"] and any(f"0x{i:04X}" in (drive["refused"] or "") for i in LIMITS)
    assert b.model.state == "SWITCH ON DISABLED"


@pytest.mark.parametrize(
    ("mode", "via"), [("envelope", "SDO"), ("counter", "SDO"), ("envelope", "RPDO")]
)
def test_a_drive_re_enabled_after_its_stop_is_stopped_again(
    tmp_path: Path, mode: str, via: str
) -> None:
    """Item 3: the budget runs out (or TPDOs come late on a loaded machine) and the guard stops
    the drive; the application opens the
    limits and writes controlword 6, 7, 15 by SDO (or RPDO1), and again whenever it sees the
    drive off."""
    with guarded_bench(
        tmp_path,
        10,
        "--initial",
        "3J",
        "--target",
        "3J",
        *REACH_FLAGS,
        with_node=False,
        mode=mode,
        gap_ms=SHORT_GAP_MS,
    ) as b:
        # released, then stopped (the budget gone, or TPDOs late: as likely before it was
        # enabled as after, on a loaded machine), or held from the start (a loaded machine's
        # timings put where it would stop beyond the budget in hand: seen with two test
        # processes and the vcan suite at once)
        wait_for(
            lambda: (
                (d := b.drive_status()) and (d["stops"] or str(d["stop_reason"]).startswith(HELD))
            ),
            show=b.drive_status,
        )
        wait_for(lambda: (d := b.drive_status()) and d["guard"] == "stopped", show=b.drive_status)
        wait_for(lambda: b.model.state == "SWITCH ON DISABLED", show=b.drive_status)
        open_limits(b.app)

        def enable() -> None:
            if b.model.state == "SWITCH ON DISABLED":
                for controlword in (6, 7, 15):
                    if via == "SDO":
                        app_write(b.app, 0x6040, controlword)
                    else:  # RPDO1 carries the controlword
                        b.app.network.send_message(0x200 + DRIVE, controlword.to_bytes(2, "little"))
                        time.sleep(0.005)

        swing(b, time.monotonic() + ATTACK_S, enable)
        final = b.stop()
    drive = assert_inside_reach_bound(b, final)
    assert drive["latched"]
    assert b.model.state in ("SWITCH ON DISABLED", "READY TO SWITCH ON", "SWITCHED ON")


def remap_tpdo1(app: canopen.RemoteNode, decoy: int) -> None:
    """What a master configuring its PDOs does: TPDO1 off, its map rewritten with ``decoy``
    where the counter 0x2011 was, on again (seven SDO transfers)."""
    cob = 0x180 + DRIVE
    sdo = app.sdo

    def w(index: int, sub: int, value: int) -> None:
        def transfer() -> None:
            sdo[index][sub].raw = value

        shared_sdo(transfer, time.sleep)

    w(0x1800, 1, cob | 0x8000_0000)
    w(0x1A00, 0, 0)
    w(0x1A00, 1, 0x6041_0010)
    w(0x1A00, 2, 0x6077_0010)
    w(0x1A00, 3, decoy << 16 | 0x20)
    w(0x1A00, 0, 3)
    w(0x1800, 1, cob)


def test_a_tpdo_remapped_behind_the_guard_stops_the_drive(tmp_path: Path) -> None:
    """Item 1 (counter mode): TPDO1 re-mapped so that a frozen object (the profile deceleration
    0x6084, set 0.2 J above the counter's reading) sits where the energy counter 0x2011 was: a
    guard that keeps its set-up map decodes a counter that never moves. The drive's reach is
    its full limits here (the application opens none): the bound is the ordinary one."""
    reach = ("--cia402-reach-torque", "265", "--cia402-reach-current", "265")
    with guarded_bench(
        tmp_path,
        10,
        *("--initial", "100J", "--target", "2J", *reach, "--cia402-reach-speed", "100500"),
        with_node=False,
        mode="counter",
        gap_ms=GAP_MS,
    ) as b:
        wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
        app_write(b.app, 0x6084, b.drawn() % 2**32 + 200_000)  # 0x2011: drawn µJ, 32 bits
        remap_tpdo1(b.app, 0x6084)
        swing(b, time.monotonic() + ATTACK_S, brake=False)
        final = b.stop()
    drive = assert_inside_reach_bound(b, final)
    # the first write of TPDO1's configuration that its read-back caught: the COB-ID switched
    # off (0x1800:1) when the read-back came between two transfers, else the map (0x1A00)
    assert drive["latched"] and any(i in (drive["refused"] or "") for i in ("0x1800", "0x1A00"))
    assert b.model.state == "SWITCH ON DISABLED"


def test_a_lowered_quick_stop_deceleration_stops_the_drive(tmp_path: Path) -> None:
    """Item 4 (counter mode, quick stop): 0x6085 lowered while the drive runs would make its
    stop draw more than the bound allows; the guard reads it back lower than at set-up and
    stops the drive for good (0x6085 raised would be fine: a faster stop draws less)."""
    quick = ("--cia402-stop", "quick", "--cia402-stop-timeout", "200ms")
    with guarded_bench(
        tmp_path,
        10,
        *("--initial", "100J", "--target", "10J", *REACH_FLAGS, *quick),
        with_node=False,
        mode="counter",
        gap_ms=GAP_MS,
    ) as b:
        wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
        app_write(b.app, 0x6085, 1_000)  # 1 rad/s² instead of 500
        swing(b, time.monotonic() + 1.0, brake=False)  # 0x6084 is watched too
        final = b.stop()
    drive = assert_inside_reach_bound(b, final)
    assert drive["latched"] and "0x6085" in (drive["refused"] or "")


def test_a_write_the_guard_cannot_see_is_found_by_the_periodic_read_back(tmp_path: Path) -> None:
    """The drive's own panel (not the bus) switches its heartbeat consumer off: the guard sees
    no frame, and its read-back every 200 ms finds 0x1016:1 changed and stops the drive."""
    with guarded_bench(
        tmp_path,
        10,
        *("--initial", "100J", "--target", "2J", *REACH_FLAGS, "--cia402-reread", "200ms"),
        with_node=False,
        mode="counter",
        gap_ms=GAP_MS,
    ) as b:
        wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
        with b.face.lock:
            b.model.write(0x1016, 1, 0)
        swing(b, time.monotonic() + 1.0)
        final = b.stop()
    granted, drive = books(final)
    assert b.drawn() <= granted + drive["bound_unseen_uj"]
    assert drive["latched"] and "periodic read-back" in drive["refused"]
    assert "0x1016:1 = 0" in drive["refused"]
    assert b.model.state == "SWITCH ON DISABLED"


@pytest.mark.parametrize(
    ("mode", "stall_s"), [("envelope", 0.3), ("envelope", 0.5), ("counter", 0.5)]
)
def test_a_guard_held_off_as_a_write_behind_it_arrives_stays_inside_the_bound(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mode: str, stall_s: float
) -> None:
    """Item 2 on a host held off (tests/test_odrive_live.py's stall, for the CiA 402 guard): the
    shared Notifier's thread, which takes in the drive's TPDOs and every frame addressed to it,
    waits ``stall_s`` at the application's first write of 0x6072, the drive running at the
    limits it opens meanwhile. The guard charges the reach from the frame's arrival (its age).
    Its bound needs no intake of its own (the ODrive and moteus guards' term): the TPDOs queued
    behind the same wait are taken in late and old, so the gap measured between two of them
    plus their age cover it, and past the PDO timeout the supervisor's loop, not held off,
    stops the drive (TPDOs stopped) and measures the gap to the next. With the TPDOs stamped at
    their arrival instead (as the ODrive link stamps its feedback) the 0.3 s wait left the
    notice: worst gap 105 ms, age 0. The bound at the reach (450 W) is far above what the
    emulated drive draws, so that check is the one that bites: 22-34 J drawn on 5 J granted,
    bounds 320-520 J with the wait, 197-238 J without it."""
    from canergy.live.canopen.cia402_link import DriveLink

    stalls: list[float] = []
    take = DriveLink._on_sdo_request

    def held_off(link: DriveLink, can_id: int, data: bytearray, stamp: float) -> None:
        writes_6072 = len(data) >= 4 and data[0] >> 5 == 1 and data[1:4] == b"\x72\x60\x00"
        if writes_6072 and not stalls:
            stalls.append(stall_s)
            time.sleep(stall_s)  # the Notifier held off: the write waits to be taken in
        take(link, can_id, data, stamp)

    monkeypatch.setattr(DriveLink, "_on_sdo_request", held_off)
    with guarded_bench(
        tmp_path,
        10,
        *("--initial", "5J", "--target", "2J", *REACH_FLAGS),
        with_node=False,
        mode=mode,
        gap_ms=GAP_MS,
    ) as b:
        wait_for(lambda: b.model.state == "OPERATION ENABLED", show=b.drive_status)
        before = b.drawn()
        swing(b, time.monotonic() + ATTACK_S, lambda: open_limits(b.app))
        final = b.stop()
    granted, drive = books(final)
    timings = drive["bound_timings_us"]
    print(
        f"{mode}, stall {stall_s} s: drawn {b.drawn()} µJ ({b.drawn() - before} µJ since enabled), "
        f"granted {granted} µJ, bound at the reach {drive['bound_reach_uj']} µJ, metered "
        f"{drive['metered_uj']} µJ, writes seen {drive['writes_seen']}, worst gap "
        f"{drive['worst_gap_us']} µs, timings {timings}, stop {drive['stop_reason']!r}"
    )
    assert stalls and drive["writes_seen"]
    # the wait is in the notice: the TPDOs behind it were taken in late (the gap between two,
    # measured) and old (their age)
    assert drive["worst_gap_us"] + timings["age"] >= stall_s * 1e6
    assert b.drawn() <= granted + drive["bound_reach_uj"], (
        b.drawn(),
        granted,
        drive["bound_reach_uj"],
    )
    assert drive["metered_uj"] >= b.drawn()
    assert drive["latched"] and b.model.state == "SWITCH ON DISABLED"
