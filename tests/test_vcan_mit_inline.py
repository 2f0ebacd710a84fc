"""``canergy inline`` as a process of its own on real SocketCAN (``pytest -m vcan``): it forwards
between vcan0, the application's bus, and vcan1, the motors' bus, where ``canergy supervisor``
(another process) grants its proxy's budget and the emulated DM4310 (``firmware_model.mit``, in
the test's process) answers. The application (the test, on vcan0 only) sends enter motor mode,
the largest feed-forward torque and, every tenth frame, the largest gains, from before the
grant until the forwarder's status file shows the budget gone: far more than the budget is
worth. The motor only ever received commands clamped under the cap; what was clamped and
refused is in the forwarder's status (each frame it took accounted for) and on its stderr; what
the motor drew stays within what the supervisor granted plus the bound the status states.

Time is driven from what the test observes: the status files, the emulator's state. Inside
user-mode Linux a process can be held off for hundreds of milliseconds: the forwarder's
feedback and stop timeouts are 2 s (``--mit-feedback-timeout``, ``--mit-stop-timeout``), its
reaction and latency allowances are raised to what it measures (and so are the clamp's horizon
and the bound); waits are minutes."""

from __future__ import annotations

import contextlib
import json
import re
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
from support.procs import Procs, python, status
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT

from firmware_model.mit.live_bench import MOTOR, NODE

pytestmark = pytest.mark.vcan

APP, MOTORS = "vcan0", "vcan1"


@pytest.fixture(scope="module", autouse=True)
def _both_up() -> None:
    interfaces_up(APP, MOTORS)


def _read(path: Path) -> dict[str, Any] | None:
    """The status file as last written (None before the first write)."""
    with contextlib.suppress(FileNotFoundError, json.JSONDecodeError):
        return dict(json.loads(path.read_text()))
    return None


def _motor(path: Path) -> dict[str, Any] | None:
    got = _read(path)
    return None if got is None else dict(got["motors"][str(MOTOR)])


def test_canergy_inline_as_a_process_holds_a_burst_to_the_budget(procs: Procs) -> None:
    tmp = procs.tmp
    inline_status = tmp / "inline.json"
    motor, face = motor_on(MOTORS)
    sup = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", MOTORS, "--nodes", str(NODE)]
    sup += ["--initial", "20J", "--target", "20J", "--max-grant", "20J", *TIMEOUT]
    sup += ["--state", str(tmp / "state.json"), "--no-fsync"]
    sup += ["--status-file", str(tmp / "sup.json"), "--status-period", "0.2"]
    procs.start("supervisor", python(*sup))
    inline = ["-m", "canergy", "inline", "-i", "socketcan", "-c", MOTORS]
    inline += ["--app-interface", "socketcan", "--app-channel", APP]
    inline += ["--mit", str(MOTOR), "--mit-nodes", str(NODE), "--mit-model", "DM4310"]
    inline += ["--mit-max-torque", str(CAP), *SLOW]
    inline += ["--status-file", str(inline_status), "--status-period", "50ms"]
    procs.start("inline", python(*inline))
    app = can.Bus(interface="socketcan", channel=APP)

    def show() -> object:
        return _read(inline_status), procs.stderr("inline")[-1500:]

    try:
        # from before the grant (refused, counted) until the status shows the budget gone;
        # enter motor mode every tenth frame too, so that the first one granted takes effect
        rounds = burst_until_spent(app, lambda: _motor(inline_status), motor, show)
        forwarder = _read(inline_status)
    finally:
        app.shutdown()
        stopped = procs.stop("inline")
        face.close()
    assert stopped == 0, procs.stderr("inline")
    assert not motor.enabled  # and told to exit once more on the way out
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert forwarder is not None
    books = status(tmp / "sup.json")["nodes"][str(NODE)]
    granted = books["delivered_uj"] - books["returns_credited_uj"]
    gate = forwarder["motors"][str(MOTOR)]
    c = gate["commands"]
    drawn, received = received_within_the_cap(motor, face)
    print(
        f"rounds {rounds}, to motors {forwarder['to_motors']}, forwarded {c['forwarded']}, "
        f"clamped {c['clamped']}, refused {c['refused']} {c['refused_why']}; motor received "
        f"{received} commands; drawn {drawn} µJ, granted {granted} µJ, bound "
        f"{gate['bound_uj']} µJ"
    )
    # every frame the forwarder took from the application is accounted for, in one snapshot
    assert c["forwarded"] + c["clamped"] + c["refused"] == forwarder["to_motors"]
    assert c["clamped"] >= 1 and c["refused"] >= 1 and forwarder["send_failures"] == 0
    lines = re.findall(r"clamped (\d+), refused (\d+)", procs.stderr("inline"))
    assert lines and min(map(int, lines[-1])) >= 1  # its last status line on stderr says so too
    assert 0 < drawn <= granted + gate["bound_uj"], (drawn, granted, gate)
