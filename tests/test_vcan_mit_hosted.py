"""``canergy supervisor --mit`` as a process of its own on real SocketCAN (``pytest -m vcan``),
as the recipe ``mit-hosted`` runs it: the supervisor and the emulated DM4310
(``firmware_model.mit``, in the test's process) on vcan0, the motors' bus; the application (the
test, on vcan1 only) on the bus the supervisor forwards from (``--mit-app-channel vcan1``). The
application sends enter motor mode, the largest feed-forward torque and, every tenth frame, the
largest gains, from when the supervisor's status shows the motor until it shows the budget gone:
far more than the budget is worth. The motor only ever received commands clamped under the cap;
what was clamped and refused is in the supervisor's status under ``cia402.devices.mit`` (each
frame the supervisor took from the application accounted for); what the motor drew stays within
what the supervisor granted plus the bound the status states.

Time is driven from what the test observes: the status file, the emulator's state. Inside
user-mode Linux a process can be held off for hundreds of milliseconds: the gates' feedback and
stop timeouts are 2 s, their reaction and latency allowances are raised to what they measure
(and so are the clamp's horizon and the bound); waits are minutes."""

from __future__ import annotations

import contextlib
import json
import time
from pathlib import Path
from typing import Any

import can
import pytest
from support.mit_vcan import (
    CAP,
    SLOW,
    burst_until_spent,
    interfaces_up,
    motor_on,
    received_within_the_cap,
)
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT

from firmware_model.mit.live_bench import MOTOR

pytestmark = pytest.mark.vcan

MOTORS, APP = "vcan0", "vcan1"


@pytest.fixture(scope="module", autouse=True)
def _both_up() -> None:
    interfaces_up(APP, MOTORS)


def _motor(path: Path) -> dict[str, Any] | None:
    """The motor's part of the status file as last written (None before it shows)."""
    with contextlib.suppress(FileNotFoundError, json.JSONDecodeError, KeyError):
        return dict(json.loads(path.read_text())["cia402"]["devices"]["mit"][str(MOTOR)])
    return None


def test_canergy_supervisor_mit_as_a_process_holds_a_burst_to_the_budget(procs: Procs) -> None:
    tmp = procs.tmp
    sup_status = tmp / "sup.json"
    motor, face = motor_on(MOTORS)
    started = time.monotonic()
    sup = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", MOTORS]
    sup += ["--initial", "20J", "--target", "20J", "--max-grant", "20J", *TIMEOUT]
    sup += ["--mit", str(MOTOR), "--mit-model", "DM4310", "--mit-max-torque", str(CAP), *SLOW]
    sup += ["--mit-app-interface", "socketcan", "--mit-app-channel", APP]
    sup += ["--state", str(tmp / "state.json"), "--no-fsync"]
    sup += ["--status-file", str(sup_status), "--status-period", "50ms"]
    procs.start("supervisor", python(*sup))
    app = can.Bus(interface="socketcan", channel=APP)

    def show() -> object:
        return _motor(sup_status), procs.stderr("supervisor")[-1500:]

    try:
        # the supervisor up and the motor known before the burst (its frames before then would
        # go nowhere: no process reads vcan1 yet)
        wait(lambda: _motor(sup_status) is not None, "the supervisor's status", 300, show)
        # from then (the grant may come before or after the first frame: refused, counted)
        # until the status shows the budget gone; enter motor mode every tenth frame too, so
        # that the first one granted takes effect
        rounds = burst_until_spent(app, lambda: _motor(sup_status), motor, show)
        gate = _motor(sup_status)
    finally:
        app.shutdown()
        stopped = procs.stop("supervisor")
        face.close()
    took = time.monotonic() - started
    assert stopped == 0, procs.stderr("supervisor")
    assert not motor.enabled  # and told to exit once more on the way out
    assert gate is not None
    books = status(sup_status)["nodes"][str(MOTOR)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    c = gate["commands"]
    drawn, received = received_within_the_cap(motor, face)
    print(
        f"rounds {rounds}, taken {gate['app_taken']}, to motors {gate['to_motors']}, forwarded "
        f"{c['forwarded']}, clamped {c['clamped']}, refused {c['refused']} {c['refused_why']}, "
        f"overflowed {gate['app_overflowed']} (peak {gate['app_queue_peak']}); motor received "
        f"{received} commands; drawn {drawn} µJ, granted {granted} µJ, bound "
        f"{gate['bound_uj']} µJ, reaction {gate['bound_timings_us']}; {took:.1f} s"
    )
    # every frame the supervisor took from the application is accounted for, in one snapshot
    judged = c["forwarded"] + c["clamped"] + c["refused"]
    others = gate["app_passed"] + gate["canergy_frames_refused"] + gate["app_for_other_devices"]
    assert (
        judged + others + gate["app_error_frames"] + gate["app_overflowed"] == (gate["app_taken"])
    ), gate
    assert gate["app_taken"] >= rounds and gate["forward_send_failures"] == 0
    assert c["clamped"] >= 1 and c["refused"] >= 1
    assert "mit motor 1: stopping (budget exhausted" in procs.stderr("supervisor")
    assert 0 < drawn <= granted + gate["bound_uj"], (drawn, granted, gate)
