"""Guarded CiA 402 drives on real SocketCAN: the supervisor, the emulated drive and a
python-canopen application as separate processes on vcan0 (``pytest -m vcan``).

Figures inside user-mode Linux are not speed figures; the bound is checked with the reaction and
stop times measured in the same run.
"""

from __future__ import annotations

import signal
import time
from typing import Any

import canopen
import pytest
from test_vcan import BUS, IFACE, Procs, _python, _status, _vcan_up, _wait, procs

from canergy.cia402.meter import overshoot_bound_uj
from canergy.ledger import ledger_from_status
from canergy.live.cia402_link import EDS

pytestmark = pytest.mark.vcan
__all__ = ["_vcan_up", "procs"]  # the fixtures of test_vcan, used here

DRIVE = 10


def _drive(procs: Procs, pdo_ms: int) -> None:
    procs.start(
        "drive",
        _python(
            "-m",
            "firmware_model.drive",
            *("--node", str(DRIVE), *BUS),
            *("--load-torque", "0.02", "--load-opposes"),
            *("--pdo-period", f"{pdo_ms}ms"),
            *("--status-file", str(procs.tmp / "drive.json"), "--status-period", "0.1"),
        ),
    )


def _guard(procs: Procs, *extra: str) -> None:
    tmp = procs.tmp
    procs.start(
        "supervisor",
        _python(
            "-m",
            "canergy",
            "supervisor",
            *BUS,
            *("--cia402", str(DRIVE), "--cia402-enable", "--cia402-resistance", "1"),
            *("--cia402-pdo-timeout", "1s", "--cia402-consumer-timeout", "1s"),
            *("--target", "1J", "--max-grant", "0.5J", "--response-timeout", "0.3"),
            *("--state", str(tmp / "state.json"), "--no-fsync"),
            *("--status-file", str(tmp / "sup.json"), "--status-period", "0.2"),
            *extra,
        ),
    )


def _guarded(procs: Procs) -> dict[str, Any]:
    path = procs.tmp / "sup.json"
    if not path.exists():
        return {}
    return dict(_status(path)["cia402"]["drives"][str(DRIVE)])


def _application(procs: Procs) -> canopen.Network:
    """Once the guard has set the drive up: profile velocity, 100 rad/s."""
    _wait(lambda: bool(_guarded(procs).get("ready")), "the guard setting the drive up")
    network = canopen.Network()
    network.connect(interface="socketcan", channel=IFACE)
    app = network.add_node(DRIVE, str(EDS))
    app.sdo.RESPONSE_TIMEOUT = 5.0
    app.sdo[0x6060].raw = 3
    app.sdo[0x6083].raw = 1_000_000
    app.sdo[0x60FF].raw = 100_000
    return network


def _history(drive: dict[str, Any], state: str, after: int = 0) -> int:
    return next(
        h["time_us"] for h in drive["history"] if h["state"] == state and h["time_us"] > after
    )


@pytest.mark.parametrize("pdo_ms", [20, 50])
def test_a_guarded_drive_on_vcan0_stops_inside_the_bound(procs: Procs, pdo_ms: int) -> None:
    tmp = procs.tmp
    _drive(procs, pdo_ms)
    _guard(procs, "--initial", "2J")
    network = _application(procs)
    try:
        _wait(
            lambda: (
                _guarded(procs).get("stop_reason") == "budget exhausted"
                and _guarded(procs).get("drive_state") == "SWITCH ON DISABLED"
            ),
            "the budget running out and the drive stopping",
            timeout_s=180,
        )
        assert int(network[DRIVE].sdo[0x6041].raw) & 0x4F == 0x40  # read beside the guard
    finally:
        network.disconnect()
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert procs.stop("drive") == 0, procs.stderr("drive")
    sup, drive = _status(tmp / "sup.json"), _status(tmp / "drive.json")
    guarded = sup["cia402"]["drives"][str(DRIVE)]
    books = sup["nodes"][str(DRIVE)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    assert granted == 2_000_000 and sup["conservation"]["holds"]
    assert ledger_from_status(sup, []).passive  # the books close over the drive's proxy
    quick_stop = _history(drive, "QUICK STOP ACTIVE")
    stop_us = _history(drive, "SWITCH ON DISABLED", after=quick_stop) - quick_stop
    bound = overshoot_bound_uj(
        round(drive["peak_power_w"] * 1e6), pdo_ms * 1000, guarded["reaction_max_us"], stop_us
    )
    print(
        f"vcan0 TPDO {pdo_ms} ms: granted {granted} µJ, drawn {drive['drawn_uj']} µJ, "
        f"reaction max {guarded['reaction_max_us']} µs, stop {stop_us} µs, bound {bound} µJ"
    )
    assert drive["drawn_uj"] <= granted + bound


def test_kill_9_of_the_host_stops_the_drive_through_its_heartbeat_consumer(procs: Procs) -> None:
    tmp = procs.tmp
    _drive(procs, 20)
    _guard(procs, "--initial", "100J")
    network = _application(procs)
    network.disconnect()
    _wait(lambda: _status(tmp / "drive.json")["state"] == "OPERATION ENABLED", "the drive running")
    time.sleep(1)
    killed_at = time.monotonic_ns() // 1000
    procs.stop("supervisor", signal.SIGKILL)
    _wait(lambda: _status(tmp / "drive.json")["state"] == "FAULT", "the drive's own fault reaction")
    assert procs.stop("drive") == 0, procs.stderr("drive")
    drive = _status(tmp / "drive.json")
    assert drive["fault_reason"] == "heartbeat consumer timeout"
    assert drive["error_code"] == 0x8130
    reaction = _history(drive, "FAULT REACTION ACTIVE")
    # the last heartbeat left before the kill: the consumer's 1 s (and a slow UML kernel's
    # scheduling, generously) bound the time from the kill to the drive's reaction
    assert killed_at < reaction <= killed_at + 1_000_000 + 500_000
    assert abs(drive["velocity_rad_s"]) < 0.05
    sup = _status(tmp / "sup.json")  # its last status before the kill
    books = sup["nodes"][str(DRIVE)]
    fault = _history(drive, "FAULT", after=reaction)
    bound = overshoot_bound_uj(
        round(drive["peak_power_w"] * 1e6), 1_000_000, reaction - killed_at, fault - reaction
    )
    # what it drew stays within what was granted (even in the last status written) plus the
    # bound over the silence and the stop
    assert drive["drawn_uj"] <= books["delivered_uj"] + 1_000_000 + bound
