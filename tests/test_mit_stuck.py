"""A motor that ignores exit motor mode, guarded in line by ``MitBus`` and by ``canergy inline``
(python-can's virtual bus, the wall clock, the emulated DM4310 with ``ignores_exit``): once its
budget is gone it keeps its last command, so it is STUCK the stop timeout after the stop. Exit
is repeated, the status and the report line say so, ``--on-stuck`` runs once (not again on the
passes that follow), and what it may draw from the stop's notice on is booked as uncontained."""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import can
import pytest

from canergy.cli import build_parser
from canergy.cli.inline import run as run_inline
from canergy.live.devices.mit_bus import MitBus, MitMotor
from firmware_model.drive.live_bench import wait_for
from firmware_model.mit.live_bench import MOTOR, NODE, STEADY, burst, rig

STOP_MS = 3000
TIMES = {"feedback_timeout_us": 2_000_000, "stop_timeout_us": STOP_MS * 1000}
"""The stop's timeout: only a reply later than the stop plus the notice the guard has measured
can show the motor powered. A fresh-clone CI run under load stopped the motor with 22.5 J of
40 J left (a bound that, at 15.36 W, allows a notice near 1.4 s: derived, the status was not
printed) and with a 1 s timeout heard nothing past it in time."""
BUDGET = "40J"
"""What the runs grant the motor: the guard's bound counts the worst reaction and latency it
has measured at the 0.5 N·m cap's 15.36 W; 40 J covers a notice of 2 s and more (with the
bench's usual 20 J a host that stalled 1.2 s left the motor held with budget in hand)."""


def relay(tmp: Path) -> tuple[str, Path]:
    """A command that appends its arguments to a file: what ``--on-stuck`` ran, a line a run."""
    cut = tmp / "relay"
    script = tmp / "relay.py"
    script.write_text("import sys\nopen(sys.argv[1], 'a').write(' '.join(sys.argv[2:]) + '\\n')\n")
    return f"{sys.executable} {script} {cut} {{profile}} {{node}}", cut


def check_stuck(status: dict[str, Any], said: list[str], cut: Path) -> None:
    assert status["guard"] == "stuck", status
    want = f"still powered {STOP_MS} ms after the stop"
    assert status["stuck"] == want, (status["stuck"], status.get("bound_timings_us"))
    assert status["on_stuck"]["runs"] == 1 and status["on_stuck"]["exit_code"] == 0
    assert cut.read_text() == "mit 1\n"  # once, the motor's CAN id filled in
    assert status["uncontained_uj"] > 0  # booked, not metered
    assert status["envelope_w"] > 15.36  # the model's whole envelope, not the closed cap's 0 W
    stuck = f"mit motor 1: STUCK (still powered {STOP_MS} ms after the stop"
    assert any(stuck in s for s in said), said


def test_mit_bus_reports_a_motor_that_ignores_exit_stuck_and_runs_on_stuck_once(
    tmp_path: Path,
) -> None:
    command, cut = relay(tmp_path)
    said: list[str] = []
    with rig(tmp_path, BUDGET) as r:
        r.model.ignores_exit = True
        bus = MitBus(
            can.Bus(interface="virtual", channel=r.channel),
            [MitMotor(MOTOR, node=NODE, model="DM4310", max_torque=0.5)],
            guard_config=TIMES,
            on_stuck=command,
            report=said.append,
        )
        try:
            wait_for(lambda: bus.status(MOTOR)["guard"] == "running", 60, lambda: bus.status(MOTOR))
            burst(bus, lambda: bus.status(MOTOR)["guard"] == "stuck", [STEADY])
            wait_for(lambda: (bus.status(MOTOR)["on_stuck"] or {}).get("exit_code") == 0, 60)
            exits = bus.counts(MOTOR).exits
            uncontained = bus.status(MOTOR)["uncontained_uj"]
            wait_for(lambda: bus.counts(MOTOR).exits >= exits + 3, timeout=60)  # repeated
            status = bus.status(MOTOR)
        finally:
            bus.shutdown()
        r.stop()
    assert r.model.enabled  # it did not obey
    check_stuck(status, said, cut)
    assert status["uncontained_uj"] > uncontained  # still booked, by the clock
    print(f"uncontained {status['uncontained_uj']} µJ, drawn {r.drawn()} µJ; said {said}")


def test_canergy_inline_reports_a_motor_that_ignores_exit_stuck_and_runs_on_stuck_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    command, cut = relay(tmp_path)
    status_file = tmp_path / "inline.json"
    with rig(tmp_path, BUDGET) as r:
        r.model.ignores_exit = True
        app_channel = f"app-{uuid.uuid4().hex}"
        argv = ["inline", "-i", "virtual", "-c", r.channel, "--app-interface", "virtual"]
        argv += ["--app-channel", app_channel, "--mit", str(MOTOR), "--mit-nodes", str(NODE)]
        argv += ["--mit-model", "DM4310", "--mit-max-torque", "0.5", "--on-stuck", command]
        argv += ["--mit-feedback-timeout", "2s", "--mit-stop-timeout", f"{STOP_MS}ms"]
        argv += ["--status-file", str(status_file), "--status-period", "50ms"]
        stop = threading.Event()
        result: list[int] = []
        args = build_parser().parse_args(argv)
        thread = threading.Thread(target=lambda: result.append(run_inline(args, stop)))
        thread.start()
        app = can.Bus(interface="virtual", channel=app_channel)

        def motor() -> dict[str, Any]:
            with contextlib.suppress(FileNotFoundError, json.JSONDecodeError):
                return dict(json.loads(status_file.read_text())["motors"][str(MOTOR)])
            return {}

        try:
            wait_for(lambda: motor().get("guard") == "running", 60, motor)
            burst(app, lambda: motor().get("guard") == "stuck", [STEADY], period_s=0.005)
            wait_for(lambda: (motor().get("on_stuck") or {}).get("exit_code") == 0, timeout=60)
            end = time.monotonic() + 0.5
            while time.monotonic() < end:  # many passes later: still one run
                time.sleep(0.05)
            status = motor()
        finally:
            stop.set()
            thread.join(timeout=30)
            app.shutdown()
        r.stop()
    assert result == [0]
    err = capsys.readouterr().err.splitlines()
    check_stuck(status, err, cut)
    assert any("canergy inline: " in line and "(STUCK: still powered" in line for line in err)
