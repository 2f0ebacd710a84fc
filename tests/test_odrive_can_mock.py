"""``canergy supervisor --odrive`` against a device nobody here wrote: the ``odrive-can``
package's ``ODriveCANMock`` (PyPI), on python-can's virtual bus passed to it explicitly, never
its default transport (its ``get_can_bus`` opens UDP multicast when ``CI`` is ``true``). The mock
answers no endpoint read, ignores Estop, takes Set_Axis_State only after 0.5 s and reports no
power: the guard refuses it at set-up, or, trusting its limits, reports it STUCK after the stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from odrive_can.mock import ODriveCANMock

from canergy.devices.odrive import AxisState, Cmd, can_id, set_axis_state
from firmware_model.odrive.live_bench import LIMITS, MOTOR, wait_for
from firmware_model.supervisor_thread import SupervisorThread, supervisor_thread

AXIS = 3


@contextlib.contextmanager
def mocked_axis(tmp: Path, *supervisor_args: str) -> Iterator[tuple[SupervisorThread, can.BusABC]]:
    """The mock as axis 3, the supervisor guarding it, and the application's bus."""
    assert os.environ.get("CI") is None  # and the bus is passed: its get_can_bus never runs
    channel = f"odrive-mock-{uuid.uuid4().hex}"
    mock_bus = can.Bus(interface="virtual", channel=channel)
    mock = ODriveCANMock(axis_id=AXIS, can_bus=mock_bus)  # type: ignore[arg-type]
    assert mock.bus is mock_bus
    loop = asyncio.new_event_loop()
    task = loop.create_task(mock.main())

    def run() -> None:
        with contextlib.suppress(asyncio.CancelledError):
            loop.run_until_complete(task)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    app = can.Bus(interface="virtual", channel=channel)
    args = (
        *("-i", "virtual", "-c", channel, "--odrive", str(AXIS)),
        *("--initial", "20J", "--target", "5J", "--max-grant", "500mJ"),
        *MOTOR,
        *LIMITS,
        *("--odrive-feedback-timeout", "2s"),
        *supervisor_args,
    )
    try:
        with supervisor_thread(tmp, *args) as supervisor:
            yield supervisor, app
    finally:
        loop.call_soon_threadsafe(task.cancel)
        thread.join(timeout=10)
        loop.close()
        mock.notifier.stop()
        mock_bus.shutdown()
        app.shutdown()


def axis(supervisor: SupervisorThread) -> dict[str, Any] | None:
    return supervisor.device("odrive", AXIS)


@pytest.fixture(autouse=True)
def not_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    """Never the mock's default transport: no ``CI`` in the environment."""
    monkeypatch.delenv("CI", raising=False)


def test_the_mock_answers_no_read_back_and_is_refused_at_set_up(tmp_path: Path) -> None:
    with mocked_axis(tmp_path, "--odrive-endpoints", "401,178") as (sup, _):
        d = wait_for(lambda: (d := axis(sup)) and d["refused"] and d, timeout=30)
    assert d["refused"].startswith("the odrive limits cannot be read back")
    assert d["usable_uj"] == 0 and d["alive"] is False


def test_the_mock_trusted_ignores_the_stop_and_is_reported_stuck(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cut = tmp_path / "relay"  # what --on-stuck ran, one line per run
    script = tmp_path / "relay.py"
    script.write_text("import sys\nopen(sys.argv[1], 'a').write(' '.join(sys.argv[2:]) + '\\n')\n")
    relay = f"{sys.executable} {script} {cut} {{profile}} {{node}}"
    with mocked_axis(
        tmp_path, "--odrive-trust-limits", "--odrive-stop-timeout", "300ms", "--on-stuck", relay
    ) as (sup, app):
        wait_for(lambda: (d := axis(sup)) and d["ready"], timeout=30)
        # its bus voltage read once before the application floods it: the mock answers a poll
        # only between the 0.5 s it takes over each Set_Axis_State, one after the other
        wait_for(lambda: (d := axis(sup)) and d["bus_voltage_v"] is not None, timeout=30)
        closed_loop = set_axis_state(AxisState.CLOSED_LOOP_CONTROL)
        frame_id = can_id(AXIS, Cmd.SET_AXIS_STATE)
        frame = can.Message(arbitration_id=frame_id, data=closed_loop, is_extended_id=False)

        def stuck() -> dict[str, Any] | None:
            app.send(frame)  # the application wants closed loop (the mock takes 0.5 s)
            d = axis(sup)
            return d if d and d["stuck"] else None

        d = wait_for(stuck, timeout=60)
        wait_for(lambda: cut.exists() and (a := axis(sup)) and a["on_stuck"]["exit_code"] == 0)
        stuck_for = time.monotonic() + 1.0
        while time.monotonic() < stuck_for:  # many passes later: still one run
            app.send(frame)
            time.sleep(0.05)
        last = axis(sup)
    assert cut.read_text() == "odrive 3\n"  # run once, the axis named
    assert last is not None and last["stuck"] and last["on_stuck"]["runs"] == 1
    # its heartbeat (every 200 ms) shows it still in closed loop, or comes too late to tell
    assert d["stuck"] in {
        f"{how} 300 ms after the stop" for how in ("still powered", "not heard for")
    }
    assert d["limits_verified"] is False
    assert d["bus_voltage_v"] == 0.0  # it reports no power
    assert f"odrive axis 3: STUCK ({d['stuck']}; stop repeated" in capsys.readouterr().err
