"""`canergy supervisor`, `canergy grant` and `python -m firmware_model` as users call them."""

from __future__ import annotations

import json
import socket
import threading
import time
import uuid
from pathlib import Path

import can
import pytest
from support.live_rig import Loop

from canergy.cli import main
from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import MAX_STATUS, request
from canergy.messages import Direction
from firmware_model.__main__ import main as firmware_main
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore


def _emulator(tmp: Path, channel: str, nodes: list[int]) -> tuple[NodeHost, Loop]:
    codec = Codec()
    now = monotonic_us()
    host = NodeHost(
        [
            FirmwareNode(n, NvStore(tmp / f"{n}.nv", n, fsync=False), NodeConfig(), now)
            for n in nodes
        ]
    )
    bus = can.Bus(interface="virtual", channel=channel)
    return host, Loop(BusRuntime(bus, host, codec=codec, receives=Direction.TO_CLIENT))


def _wait_for(path: Path) -> None:
    """Until a connection to the control socket at ``path`` is accepted (the file appears a
    moment before the socket listens; a thread of this process can land in that moment)."""
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            try:
                probe.connect(str(path))
            except (FileNotFoundError, ConnectionRefusedError):
                time.sleep(0.02)
            else:
                return


def test_grant_as_a_single_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    channel = f"cli-{uuid.uuid4().hex}"
    host, loop = _emulator(tmp_path, channel, [4])
    try:
        args = ["grant", "-i", "virtual", "-c", channel, "--node", "4", "--amount", "2J"]
        assert main([*args, "--state", str(tmp_path / "s.json"), "--initial", "5J"]) == 0
        answer = json.loads(capsys.readouterr().out)
        assert answer["outcome"] == "COMMITTED" and answer["amount_uj"] == 2_000_000
        state = json.loads((tmp_path / "s.json").read_text())
        assert state["usable_uj"] == 3_000_000
        # a second run continues from the state file; asking for more than is left is refused
        assert main([*args, "--state", str(tmp_path / "s.json"), "--amount", "4J"]) == 1
        refused = capsys.readouterr().out
        assert "refused" in refused and "the supervisor has 3.000000 J left" in refused  # why
    finally:
        loop.halt()
    assert host.nodes[4].client.state.usable == 2_000_000


def test_the_cores_continue_each_others_books(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One state file, grants by the Python core and the compiled one in turn: each takes
    the other's books as its own (the file is the service's, not the core's)."""
    channel = f"cli-{uuid.uuid4().hex}"
    host, loop = _emulator(tmp_path, channel, [2])
    state = tmp_path / "s.json"
    try:
        base = ["grant", "-i", "virtual", "-c", channel, "--state", str(state), "--node", "2"]
        for core in ("python", "c", "python", "c"):
            assert main([*base, "--amount", "1J", "--initial", "5J", "--core", core]) == 0
        answers = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        assert [a["tx"] for a in answers] == [1, 2, 3, 4]
    finally:
        loop.halt()
    books = json.loads(state.read_text())
    assert books["usable_uj"] == 1_000_000 and books["sessions"]["2"]["delivered_uj"] == 4_000_000
    assert host.nodes[2].client.state.usable == 4_000_000


def test_a_single_run_grant_keeps_the_books_of_the_other_nodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Found following the README: a state file with books for nodes 1-5 refused `grant --node
    3` ("not in --nodes; add them to --nodes"), and grant has no --nodes."""
    channel = f"cli-{uuid.uuid4().hex}"
    _, loop = _emulator(tmp_path, channel, [2, 3])
    state = tmp_path / "s.json"
    try:
        base = ["grant", "-i", "virtual", "-c", channel, "--state", str(state)]
        assert main([*base, "--node", "2", "--amount", "1J", "--initial", "5J"]) == 0
        assert main([*base, "--node", "3", "--amount", "0.5J"]) == 0
        answers = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        assert [a["outcome"] for a in answers] == ["COMMITTED", "COMMITTED"]
    finally:
        loop.halt()
    books = json.loads(state.read_text())
    assert books["sessions"]["2"]["delivered_uj"] == 1_000_000  # kept by the second run
    assert books["sessions"]["3"]["delivered_uj"] == 500_000
    assert books["usable_uj"] == 3_500_000


@pytest.mark.parametrize("core", ["python", "c"])
def test_supervisor_serves_grants_over_its_control_socket(tmp_path: Path, core: str) -> None:
    channel = f"cli-{uuid.uuid4().hex}"
    host, loop = _emulator(tmp_path, channel, [1, 2])
    control = tmp_path / "ctl.sock"
    status = tmp_path / "status.json"
    argv = [
        "supervisor",
        "-i",
        "virtual",
        "-c",
        channel,
        "--nodes",
        "1-2",
        "--initial",
        "10J",
        "--state",
        str(tmp_path / "s.json"),
        "--status-file",
        str(status),
        "--control",
        str(control),
        "--max-grant",
        "3J",
        "--no-fsync",
        "--core",
        core,
    ]
    result: list[int] = []
    # a daemon: a failed assertion below must fail the test, not leave the run waiting for it
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    try:
        _wait_for(control)
        answer = request(control, {"grant": {"node": 2, "amount_uj": 2_500_000}}, 30)
        assert answer["outcome"] == "COMMITTED", answer
        too_much = request(control, {"grant": {"node": 1, "amount_uj": 3_500_000}}, 30)
        assert "refused" in too_much["error"]  # above --max-grant
        assert "error" in request(control, {"grant": {"node": 9, "amount_uj": 1000}}, 30)
        assert request(control, {"stop": True}, 30) == {"stopping": True}
        thread.join(timeout=60)
    finally:
        loop.halt()
    assert result == [0]
    final = json.loads(status.read_text())
    assert final["core"] == core
    assert final["usable_uj"] == 7_500_000 and final["nodes"]["2"]["delivered_uj"] == 2_500_000
    assert (
        final["conservation"]["holds"] and final["frames_sent"] >= 2
    )  # INTENTION, COMMIT (+ re-sends)
    assert host.nodes[2].client.state.usable == 2_500_000


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["supervisor", "--nodes", "0-3"], "ids are 1-127"),
        (["supervisor", "--nodes", "1", "--initial", "lots"], "not an energy"),
        (["supervisor", "--nodes", "1", "--rate", "2J"], "unknown power unit"),
        (["supervisor", "--nodes", "1", "--core", "fast"], "invalid choice"),
        (
            [
                *("grant", "--node", "1", "--amount", "1J", "-i", "virtual", "--state", "s.json"),
                *("--core", "c", "--variant", "paper"),
            ],
            "--core c: it runs the hardened and witnessed rules only",
        ),
        (["grant", "--node", "1", "--amount", "1J", "-i", "nosuchbus"], "invalid choice"),
        *(
            (["grant", "--node", "1", "--amount", a, "-i", "virtual"], "whole millijoules")
            for a in ("0", "0.5mJ", "70J", "1500uJ")
        ),
        (
            [
                "grant",
                "--node",
                "1",
                "--amount",
                "1J",
                "--state",
                "s.json",
                "-i",
                "slcan",
                "-c",
                "/x",
            ],
            "cannot open",
        ),
        (["grant", "--node", "1", "--amount", "1J", "--state", "s.json"], "give -i/--interface"),
        (["grant", "--node", "1", "--amount", "1J", "-i", "virtual"], "--state PATH is required"),
    ],
)
def test_bad_values_get_clear_errors(
    argv: list[str],
    message: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    monkeypatch.chdir(tmp_path)  # a refusal after the books are taken leaves their lock file
    try:
        code = main(argv)
    except SystemExit as exc:
        code = int(exc.code or 0)
    assert code == 2
    assert message in capsys.readouterr().err


def test_firmware_model_rejects_bad_values(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        firmware_main(["--node", "200", "--nv", "x.nv"])
    assert exc.value.code == 2 and "outside 1..127" in capsys.readouterr().err


def test_listen_only_never_sends(tmp_path: Path) -> None:
    channel = f"cli-{uuid.uuid4().hex}"
    host, loop = _emulator(tmp_path, channel, [3])
    control = tmp_path / "ctl.sock"
    argv = [
        "supervisor",
        "-i",
        "virtual",
        "-c",
        channel,
        "--nodes",
        "3",
        "--target",
        "1J",
        "--listen-only",
        "--control",
        str(control),
        "--status-file",
        str(tmp_path / "s.json"),
    ]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)))
    thread.start()
    try:
        _wait_for(control)
        time.sleep(1.5)  # telemetry arrives; a supervisor that sends would grant now
        status = request(control, {"status": True}, 30, max_answer=MAX_STATUS)
        refused = request(control, {"grant": {"node": 3, "amount_uj": 1000}}, 30)
        assert "listen-only" in refused["error"]
        request(control, {"stop": True}, 30)
        thread.join(timeout=60)
    finally:
        loop.halt()
    assert result == [0] and status["listen_only"] and status["frames_sent"] == 0
    assert status["frames_received"] >= 1 and host.nodes[3].client.state.credited == 0


@pytest.mark.parametrize(
    ("command", "option"),
    [
        (["supervisor", "--nodes", "1"], "--state"),
        (["supervisor", "--nodes", "1", "--state", "s.json"], "--status-file"),
        (["grant", "--node", "1", "--amount", "1J"], "--state"),
    ],
)
def test_file_in_a_missing_directory_is_named_at_start(
    command: list[str], option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "no" / "such"
    argv = [*command, "-i", "virtual", "-c", uuid.uuid4().hex, option, str(missing / "f.json")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert f"cannot write {option} {missing / 'f.json'}: no directory {missing}" in err, err
    assert not (tmp_path / "no").exists()


def test_firmware_status_file_in_a_missing_directory_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "no"
    argv = ["--node", "1", "--nv", str(tmp_path / "1.nv"), "--status-file", str(missing / "s")]
    with pytest.raises(SystemExit) as exc:
        firmware_main([*argv, "-i", "virtual", "-c", uuid.uuid4().hex])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"no directory {missing}" in err and "Traceback" not in err


def test_read_only_directory_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from canergy.live import atomic

    monkeypatch.setattr(atomic.os, "access", lambda path, mode: False)  # root may write anyway
    with pytest.raises(PermissionError, match=f"--state .*: directory {tmp_path} is not writable"):
        atomic.check_writable_dir(tmp_path / "s.json", "--state")
    monkeypatch.undo()
    atomic.check_writable_dir(tmp_path / "s.json", "--state")


def test_a_grant_to_a_node_never_heard_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """No frame from the node (or it is still joining): nothing is granted, and the answer says
    why instead of a write-off after retries."""
    channel = f"cli-{uuid.uuid4().hex}"
    argv = ["grant", "-i", "virtual", "-c", channel, "--node", "9", "--amount", "1J"]
    state = str(tmp_path / "s.json")
    assert main([*argv, "--state", state, "--timeout", "0.3", "--stop-timeout", "0.1"]) == 1
    answer = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "never heard" in answer["error"]
    saved = json.loads((tmp_path / "s.json").read_text())
    assert saved["usable_uj"] == saved["initial_uj"]  # nothing reserved, nothing written off
