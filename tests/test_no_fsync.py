"""``--no-fsync`` is for tests, and a run that uses it says so (review rv3, F9): one warning on
stderr at start, and ``"fsync": false`` in its status, on ``canergy supervisor``, ``grant``,
``gateway`` and ``python -m firmware_model``. A power cut during such a run can leave an older
image of its records."""

from __future__ import annotations

import json
import uuid
from pathlib import Path
from typing import Any

import pytest

import firmware_model.__main__ as firmware
from canergy.cli import gateway as gateway_cli
from canergy.cli import grant as grant_cli
from canergy.cli import main
from canergy.cli import supervisor as supervisor_cli
from canergy.live.atomic import NO_FSYNC_WARNING

pytestmark = pytest.mark.usefixtures("both_cores")


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if NO_FSYNC_WARNING in line]


@pytest.fixture
def statuses(monkeypatch: pytest.MonkeyPatch) -> list[dict[str, Any]]:
    """Each supervisor, grant or gateway run's status where its loop would start (it ends
    there)."""
    seen: list[dict[str, Any]] = []

    def serve(loop: Any, service: Any, control: Any, **kw: Any) -> None:
        seen.append(service.status())

    for cli in (supervisor_cli, grant_cli, gateway_cli):
        monkeypatch.setattr(cli, "serve_supervisor", serve)
    return seen


def _bus() -> list[str]:
    return ["-i", "virtual", "-c", f"nofsync-{uuid.uuid4().hex}"]


@pytest.mark.parametrize("no_fsync", [True, False])
@pytest.mark.parametrize(
    "command",
    [
        ["supervisor", "--nodes", "1-2", "--initial", "1J"],
        ["grant", "--node", "1", "--amount", "1J", "--timeout", "10ms"],
        ["gateway", "--node", "20", "--nodes", "1", "--upstream-interface", "virtual"],
    ],
    ids=["supervisor", "grant", "gateway"],
)
def test_a_run_without_fsync_says_so_once_and_in_its_status(
    command: list[str],
    no_fsync: bool,
    tmp_path: Path,
    statuses: list[dict[str, Any]],
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = [*command, *_bus(), "--state", str(tmp_path / "s.json")]
    if command[0] == "gateway":
        argv += ["--upstream-channel", f"nofsync-up-{uuid.uuid4().hex}"]
    main([*argv, *(["--no-fsync"] if no_fsync else [])])
    err = capsys.readouterr().err
    assert len(statuses) == 1, err
    assert statuses[0]["fsync"] is not no_fsync
    warnings = _warnings(err)
    if no_fsync:
        assert warnings == [f"canergy {command[0]}: warning: {NO_FSYNC_WARNING}"], err
        assert "power cut" in warnings[0] and "older image" in warnings[0]
    else:
        assert warnings == [], err


@pytest.mark.parametrize("no_fsync", [True, False])
def test_the_emulator_without_fsync_says_so_once_and_in_its_status(
    no_fsync: bool,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(firmware, "_serve", lambda *args: None)  # ends where it would serve
    monkeypatch.setattr(firmware, "_Signals", lambda: None)
    argv = ["--nodes", "1-2", "--nv", str(tmp_path / "nv"), *_bus()]
    assert firmware.main([*argv, *(["--no-fsync"] if no_fsync else [])]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["fsync"] is not no_fsync
    expected = [f"python -m firmware_model: warning: {NO_FSYNC_WARNING}"] if no_fsync else []
    assert _warnings(err) == expected, err
