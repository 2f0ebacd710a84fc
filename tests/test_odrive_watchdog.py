"""The ODrive axis's own watchdog, read back (``canergy.devices.watchdog``): the supervisor on
python-can's virtual bus against the emulated axis (``firmware_model.odrive``), the watchdog's
endpoints given (``--odrive-watchdog-endpoints``) or not."""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Any

import pytest

from canergy.cli import main
from canergy.devices.odrive import AxisState, Cmd
from canergy.devices.watchdog import WatchdogCheck, WatchdogPolicy, WatchdogReading
from firmware_model.odrive.axis import WATCHDOG_EXPIRED, AxisModel
from firmware_model.odrive.live_bench import (
    ENDPOINTS,
    LIMITS,
    WATCHDOG,
    AxisBench,
    guarded_axis,
    wait_for,
)

BUDGET = ("--initial", "20J", "--target", "5J")
KIND = "odrive axis.config.enable_watchdog, watchdog_timeout"


def set_up(bench: AxisBench) -> dict[str, Any]:
    """The axis's status once set up and its watchdog read."""
    return wait_for(  # type: ignore[no-any-return]
        lambda: (
            (d := bench.axis_status())
            and d["ready"]
            and d["watchdog"]["state"] != "not read yet"
            and d
        ),
        timeout=60,
    )


def test_a_watchdog_that_is_off_refuses_the_axis(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A new ODrive's watchdog is off: the axis would run on at its last limits after the
    supervisor died. Without the read-back the guard took it and granted it budget."""
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *WATCHDOG, *BUDGET) as b:
        d = wait_for(lambda: (d := b.axis_status()) and d["refused"] and d, timeout=60)
        final = b.stop()
    assert d["refused"] == (
        f"watchdog off (disabled) ({KIND}); accept it with --odrive-allow-unwatched"
    )
    w = d["watchdog"]
    assert w["state"] == "off" and w["enabled"] is False and w["verified"] is True
    assert w["after_exit"] == "unbounded" and w["after_exit_uj"] is None
    axis = final["cia402"]["devices"]["odrive"]["3"]
    assert axis["alive"] is False and final["nodes"]["3"]["delivered_uj"] == 0
    assert f"odrive axis 3: refused: {d['refused']}" in capsys.readouterr().err


def test_an_armed_watchdog_is_shown_with_what_the_axis_may_draw_after_the_exit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with guarded_axis(
        tmp_path,
        *LIMITS,
        *ENDPOINTS,
        *WATCHDOG,
        *BUDGET,
        enable_watchdog=True,
        watchdog_timeout=0.5,
    ) as b:
        d = set_up(b)
        b.stop()
    assert d["refused"] is None
    w = d["watchdog"]
    assert w["state"] == "armed" and w["enabled"] is True and w["timeout_s"] == 0.5
    assert w["verified"] is True and w["problem"] is None and w["max_s"] == 1.0
    # the full envelope (6.77 W) for the watchdog's 0.5 s
    assert math.isclose(w["after_exit_uj"], d["envelope_full_w"] * 0.5e6, rel_tol=1e-3)
    assert "feeds" in w["after_exit"] or "fed" in w["after_exit"]
    assert "watchdog" not in capsys.readouterr().err


def test_a_watchdog_turned_off_behind_the_guard_is_found_by_the_periodic_read_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Disabled where the guard cannot see (over USB: set in the emulator directly) after the
    set-up: the read-back every second finds it and stops the axis for good."""
    with guarded_axis(
        tmp_path,
        *LIMITS,
        *ENDPOINTS,
        *WATCHDOG,
        *BUDGET,
        enable_watchdog=True,
        watchdog_timeout=0.5,
    ) as b:
        set_up(b)
        with b.face.lock:
            b.model.enable_watchdog = False
        d = wait_for(lambda: (d := b.axis_status()) and d["refused"] and d, timeout=30)
        b.stop()
    assert d["refused"] == (
        "watchdog changed behind the guard (a periodic read-back): off (disabled), was "
        "enabled, timeout 0.5 s"
    )
    assert d["latched"] and d["watchdog"]["changes"] == 1
    assert d["watchdog"]["state"] == "off"
    assert "odrive axis 3: refused: watchdog changed behind the guard" in capsys.readouterr().err


def test_a_watchdog_too_long_is_accepted_only_on_request_and_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = {"enable_watchdog": True, "watchdog_timeout": 5.0}
    (tmp_path / "refused").mkdir()
    (tmp_path / "allowed").mkdir()
    with guarded_axis(tmp_path / "refused", *LIMITS, *ENDPOINTS, *WATCHDOG, *BUDGET, **model) as b:
        d = wait_for(lambda: (d := b.axis_status()) and d["refused"] and d, timeout=60)
        b.stop()
    assert d["refused"].startswith("watchdog timeout 5 s, longer than 1 s")
    allow = ("--odrive-allow-unwatched", "--odrive-max-watchdog", "2s")
    bench = guarded_axis(
        tmp_path / "allowed", *LIMITS, *ENDPOINTS, *WATCHDOG, *allow, *BUDGET, **model
    )
    with bench as b:
        d = set_up(b)
        b.stop()
    w = d["watchdog"]
    assert d["refused"] is None and w["state"] == "too long" and w["accepted"] is True
    assert w["problem"] == "timeout 5 s, longer than 2 s"
    assert math.isclose(w["after_exit_uj"], d["envelope_full_w"] * 5e6, rel_tol=1e-3)
    err = capsys.readouterr().err
    assert (
        "odrive axis 3: watchdog timeout 5 s, longer than 2 s, accepted "
        "(--odrive-allow-unwatched)" in err
    )


def test_without_watchdog_endpoints_the_status_and_stderr_say_it_is_not_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with guarded_axis(tmp_path, *LIMITS, *ENDPOINTS, *BUDGET) as b:
        d = set_up(b)
        b.stop()
    w = d["watchdog"]
    assert d["refused"] is None
    assert w["state"] == "not read" and w["after_exit"] == "unbounded"
    assert w["problem"] == "give --odrive-watchdog-endpoints ENABLE,TIMEOUT to read it"
    assert capsys.readouterr().err.count("the axes' watchdog is not read") == 1


def test_firmware_0_5_cannot_read_the_watchdog(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["supervisor", "-i", "virtual", "-c", "x", "--odrive", "3", "--odrive-firmware"]
    argv += ["0.5", "--odrive-torque-constant", "0.05", *LIMITS, "--odrive-trust-limits"]
    argv += [*WATCHDOG, "--state", str(tmp_path / "s")]
    assert main(argv) == 2
    assert "--odrive-watchdog-endpoints: firmware 0.5" in capsys.readouterr().err


def test_an_unanswered_watchdog_refuses_unless_allowed() -> None:
    check = WatchdogCheck(WatchdogPolicy(KIND))
    assert check.take(0, None, periodic=False) == (
        f"watchdog not read back (the device did not answer) ({KIND}); accept it with "
        "--odrive-allow-unwatched"
    )
    assert check.status(10**15)["state"] == "unanswered"
    allowed = WatchdogCheck(WatchdogPolicy(KIND, allow=True))
    assert allowed.take(0, None, periodic=False) is None
    assert allowed.note() == (
        "watchdog not read back (the device did not answer), accepted "
        "(--odrive-allow-unwatched): after the supervisor's exit unbounded"
    )
    # a periodic read left unanswered is the limits' read-back's to judge
    armed = WatchdogCheck(WatchdogPolicy(KIND))
    assert armed.take(0, WatchdogReading(True, 0.2), periodic=False) is None
    assert armed.take(1, None, periodic=True) is None
    assert armed.status(10**15)["after_exit_uj"] == 200_000  # 1 W for 0.2 s


def test_a_device_without_a_watchdog_says_none() -> None:
    check = WatchdogCheck(WatchdogPolicy("cubemars ak", exists=False, read=False))
    status = check.status(10**15)
    assert status["state"] == "none" and status["after_exit"] == "unbounded"
    assert check.note() is None


def test_the_emulated_watchdog_idles_an_axis_not_fed() -> None:
    axis = AxisModel(3, 0, enable_watchdog=True, watchdog_timeout=0.1)
    axis.receive(Cmd.SET_AXIS_STATE, struct.pack("<I4x", AxisState.CLOSED_LOOP_CONTROL), False)
    axis.advance(90_000)
    axis.receive(Cmd.SET_INPUT_TORQUE, struct.pack("<ff", 0.0, 0.0), False)  # fed at 90 ms
    axis.advance(180_000)
    assert axis.state is AxisState.CLOSED_LOOP_CONTROL
    axis.advance(200_000)
    assert axis.state is AxisState.IDLE and axis.error & WATCHDOG_EXPIRED["0.6"]
