"""``--on-stuck CMD`` (canergy.live.devices.on_stuck): the command that cuts a STUCK device's
supply runs once per episode, with the device named, never blocking or breaking the loop."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from canergy.live.devices.on_stuck import OnStuck, OnStuckError, parse_on_stuck


def _wait(done: object, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while not done():  # type: ignore[operator]
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


def _recorder(out: Path) -> str:
    """A command appending its arguments and the environment it was given to ``out``."""
    script = (
        "import os, sys; "
        f"open({str(out)!r}, 'a').write(' '.join(sys.argv[1:]) + ' ' + "
        "os.environ['CANERGY_STUCK_REASON'] + '\\n')"
    )
    return f'{sys.executable} -c "{script}" {{profile}} {{node}}'


def test_it_runs_once_per_episode_naming_the_device(tmp_path: Path) -> None:
    out = tmp_path / "runs"
    told: list[str] = []
    hook = OnStuck(_recorder(out), told.append)
    for _ in range(5):  # every loop pass while the axis stays stuck
        hook("odrive", 3, "still powered 500 ms after the stop")
    hook("odrive", 4, None)
    _wait(lambda: hook.status(3) and hook.status(3)["exit_code"] == 0)  # type: ignore[index]
    assert out.read_text().splitlines() == ["odrive 3 still powered 500 ms after the stop"]
    assert hook.status(4) is None and hook.status(3)["runs"] == 1  # type: ignore[index]
    hook("odrive", 3, None)  # it obeyed after all
    hook("odrive", 3, "not heard for 500 ms after the stop")  # a new episode
    _wait(lambda: hook.status(3)["runs"] == 2 and hook.status(3)["exit_code"] == 0)  # type: ignore[index]
    assert out.read_text().splitlines()[1] == "odrive 3 not heard for 500 ms after the stop"
    assert sum("started" in line for line in told) == 2


def test_a_failing_or_missing_command_is_told_not_raised(tmp_path: Path) -> None:
    told: list[str] = []
    hook = OnStuck(f"{sys.executable} -c 'raise SystemExit(3)'", told.append)
    hook("moteus", 1, "feedback gone")
    _wait(lambda: any("exited 3" in line for line in told))
    assert hook.status(1)["exit_code"] == 3  # type: ignore[index]
    missing = OnStuck(str(tmp_path / "no-such-relay"), told.append)
    missing("mit", 2, "feedback gone")
    assert missing.status(2)["error"] and "could not start" in told[-1]  # type: ignore[index]


@pytest.mark.parametrize("text", ["", "   ", "relay 'off"])
def test_a_value_that_is_no_command_line_is_refused(text: str) -> None:
    with pytest.raises(OnStuckError):
        parse_on_stuck(text)
