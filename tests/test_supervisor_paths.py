"""`canergy supervisor` at start (issue 13): its files never clobber one another or anything else,
``--inject`` adds energy exactly once, and no configuration plans a node above its record."""

from __future__ import annotations

import json
import os
import socket
import stat
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from support.procs import Procs, python, wait
from support.procs import procs as procs  # the fixture
from support.stderr import without_no_fsync

from canergy.cli import grant as grant_cli
from canergy.cli import main
from canergy.cli import supervisor as supervisor_cli
from canergy.codec import Codec
from canergy.core import Supervisor
from canergy.live.supervisor.build import build_service
from canergy.live.supervisor.control import ControlServer, request
from canergy.live.supervisor.policy import Limits, capped_grant
from canergy.live.supervisor.service import ServiceConfig, SupervisorService
from canergy.live.supervisor.state_file import load_state
from canergy.messages import QUANTUM_UJ, USABLE_MAX_UJ, Intention, Telemetry

J = 1_000_000
RunMain = Callable[[list[str]], tuple[int, str]]


@pytest.fixture
def started(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[dict[str, Any]]]:
    """Replace the supervisor's loop: each run starts, notes what it sees, and ends at once."""
    seen: list[dict[str, Any]] = []

    def serve(runtime: Any, service: Any, control: Any, **kw: Any) -> None:
        state_path = service.config.state_path
        on_disk = json.loads(state_path.read_text()) if state_path is not None else None
        seen.append({"status": service.status(), "state_on_disk": on_disk})

    monkeypatch.setattr(supervisor_cli, "serve_supervisor", serve)
    monkeypatch.setattr(grant_cli, "serve_supervisor", serve)
    yield seen


@pytest.fixture
def run(capsys: pytest.CaptureFixture[str]) -> RunMain:
    def run_main(argv: list[str]) -> tuple[int, str]:
        code = main(argv)
        return code, without_no_fsync(capsys.readouterr().err)

    return run_main


def _supervisor(*extra: str) -> list[str]:
    bus = ["-i", "virtual", "-c", f"paths-{uuid.uuid4().hex}"]
    return ["supervisor", *bus, "--nodes", "1-2", "--no-fsync", *extra]


def _refused(code: int, err: str, *words: str) -> None:
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err


# -- paths -----------------------------------------------------------------------------------


def test_control_on_the_state_file_is_refused_and_the_books_survive(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    state = tmp_path / "s.json"
    assert run(_supervisor("--state", str(state), "--initial", "3J"))[0] == 0
    books = state.read_bytes()
    code, err = run(_supervisor("--state", str(state), "--control", str(state)))
    _refused(code, err, f"--control {state} and --state {state} name the same file")
    assert state.read_bytes() == books and len(started) == 1


@pytest.mark.parametrize("output", ["--state", "--status-file"])
def test_a_file_the_run_writes_on_its_key_file_is_refused_and_the_key_survives(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]], output: str
) -> None:
    """The key is read at start and the state or status written over it afterwards: the next
    start would have no key."""
    key = tmp_path / "m.key"
    assert run(["keys", "-o", str(key)])[0] == 0
    alias = tmp_path / "alias.key"
    alias.symlink_to(key.name)
    text = key.read_text()
    files = {"--state": str(tmp_path / "s.json"), output: str(alias)}
    code, err = run(_supervisor(*(w for pair in files.items() for w in pair), "--auth", str(key)))
    _refused(code, err, f"--auth {key} and {output} {alias} name the same file")
    assert key.read_text() == text and not started


@pytest.mark.parametrize("how", ["same", "relative", "symlink", "hardlink"])
def test_status_file_on_the_state_file_is_refused(
    tmp_path: Path,
    run: RunMain,
    started: list[dict[str, Any]],
    monkeypatch: pytest.MonkeyPatch,
    how: str,
) -> None:
    state = tmp_path / "s.json"
    state.write_text("{}")  # refused before it is read: the check comes first
    monkeypatch.chdir(tmp_path)
    other = {
        "same": state,
        "relative": Path("sub/../s.json"),
        "symlink": tmp_path / "link.json",
        "hardlink": tmp_path / "hard.json",
    }[how]
    (tmp_path / "sub").mkdir()
    if how == "symlink":
        other.symlink_to("s.json")
    elif how == "hardlink":
        os.link(state, other)
    code, err = run(_supervisor("--state", str(state), "--status-file", str(other)))
    _refused(code, err, f"--status-file {other} and --state {state} name the same file")
    assert state.read_text() == "{}" and not started


def test_status_file_and_control_on_one_path_are_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    out = tmp_path / "out"
    argv = ["--state", str(tmp_path / "s.json"), "--status-file", str(out), "--control", str(out)]
    code, err = run(_supervisor(*argv))
    _refused(code, err, f"--control {out} and --status-file {out} name the same file")
    assert not out.exists() and not (tmp_path / "s.json").exists()


def test_control_on_a_file_that_is_no_socket_is_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    precious = tmp_path / "notes.txt"
    precious.write_text("keep me")
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), "--control", str(precious)))
    _refused(code, err, f"--control {precious} exists and is not a socket")
    assert precious.read_text() == "keep me" and not (tmp_path / "s.json").exists()


def test_control_in_a_missing_directory_is_named_before_any_file_is_written(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    missing = tmp_path / "no" / "ctl.sock"
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), "--control", str(missing)))
    _refused(code, err, f"cannot write --control {missing}: no directory {missing.parent}")
    assert not (tmp_path / "s.json").exists()


def test_a_too_long_control_path_is_named(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    long = tmp_path / ("c" * 120)
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), "--control", str(long)))
    _refused(code, err, "--control", "too long for a UNIX socket")
    assert not (tmp_path / "s.json").exists()


def test_a_status_file_that_is_a_directory_is_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    folder = tmp_path / "status"
    folder.mkdir()
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), "--status-file", str(folder)))
    _refused(code, err, f"cannot write --status-file {folder}: it is a directory")


def test_a_stale_socket_is_replaced_and_removed_at_exit(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    ctl = tmp_path / "ctl.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as dead:
        dead.bind(str(ctl))  # closed without unlinking: what a killed supervisor leaves
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), "--control", str(ctl)))
    assert code == 0, err
    assert len(started) == 1 and not ctl.exists()


def test_a_socket_a_supervisor_listens_on_is_left_alone(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    ctl = tmp_path / "ctl.sock"
    live = ControlServer(ctl)
    try:
        code, err = run(_supervisor("--state", str(tmp_path / "s.json"), "--control", str(ctl)))
        _refused(code, err, f"--control {ctl}: a supervisor is already listening there")
        assert _ask_status(ctl, live) == {"status": "ok"}  # the first server still answers
    finally:
        live.close()
    assert not ctl.exists()


def _ask_status(ctl: Path, live: ControlServer) -> dict[str, Any]:
    """One request through ``live``, answered by hand as the supervisor's loop would."""
    result: list[dict[str, Any]] = []
    asker = threading.Thread(target=lambda: result.append(request(ctl, {"status": True}, 10)))
    asker.start()
    for _ in range(500):
        pending = [p for p in live.pending() if p[0].get("status") is True]
        if pending:
            pending[0][1]({"status": "ok"})
            break
        asker.join(0.01)
    asker.join(10)
    return result[0]


def test_the_server_removes_only_the_socket_it_made(tmp_path: Path) -> None:
    ctl = tmp_path / "ctl.sock"
    server = ControlServer(ctl)
    ctl.unlink()
    ctl.write_text("someone else's file")  # the path was taken over while it ran
    server.close()
    assert ctl.read_text() == "someone else's file"


def test_the_control_socket_appears_only_once_it_listens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A client that connects as soon as the file is there (what scripts and tests do) is never
    refused: between the bind and the listen nothing is at the path yet."""
    ctl = tmp_path / "ctl.sock"
    seen: list[bool] = []
    listen = socket.socket.listen

    def watched(sock: socket.socket, backlog: int) -> None:
        seen.append(ctl.exists())
        listen(sock, backlog)

    monkeypatch.setattr(socket.socket, "listen", watched)
    server = ControlServer(ctl)
    try:
        assert seen == [False]
        assert _ask_status(ctl, server) == {"status": "ok"}
        assert sorted(p.name for p in tmp_path.iterdir()) == ["ctl.sock"]  # no temporary left
        assert stat.S_IMODE(os.lstat(ctl).st_mode) == 0o600
    finally:
        server.close()
    assert not ctl.exists()


def test_a_path_taken_between_the_check_and_the_rename_is_left_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ctl = tmp_path / "ctl.sock"
    listen = socket.socket.listen

    def racing(sock: socket.socket, backlog: int) -> None:
        listen(sock, backlog)
        ctl.write_text("another process's file")  # after the check, before the rename

    monkeypatch.setattr(socket.socket, "listen", racing)
    with pytest.raises(ValueError, match="another process took it"):
        ControlServer(ctl)
    assert ctl.read_text() == "another process's file"
    assert [p.name for p in tmp_path.iterdir()] == ["ctl.sock"]


# -- --inject --------------------------------------------------------------------------------


def test_inject_adds_once_per_run_and_is_saved_before_any_grant(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    state = tmp_path / "s.json"
    code, err = run(_supervisor("--state", str(state), "--initial", "10J", "--inject", "5J"))
    assert code == 0, err
    assert "injected 5.000000J" in err and str(state) in err
    first = started[0]
    assert first["state_on_disk"]["usable_uj"] == 15 * J  # on disk when the loop starts
    assert first["state_on_disk"]["injected_uj"] == 5 * J
    assert first["status"]["injected_this_run_uj"] == 5 * J
    assert first["status"]["injected_uj"] == 5 * J and first["status"]["conservation"]["holds"]

    assert run(_supervisor("--state", str(state)))[0] == 0  # no --inject: nothing added
    assert started[1]["status"]["injected_this_run_uj"] == 0
    assert run(_supervisor("--state", str(state), "--inject", "2J"))[0] == 0
    books = load_state(state, "hardened", (1, 2))
    assert (books.initial, books.usable, books.injected) == (10 * J, 17 * J, 7 * J)


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--listen-only"], "--inject needs"),
        (["--state", "s.json", "--inject", "0J"], "--inject needs an energy above 0"),
    ],
)
def test_inject_that_could_not_be_kept_is_refused(
    tmp_path: Path,
    run: RunMain,
    started: list[dict[str, Any]],
    monkeypatch: pytest.MonkeyPatch,
    extra: list[str],
    words: str,
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = _supervisor(*extra)
    if "--inject" not in argv:
        argv += ["--inject", "5J"]
    code, err = run(argv)
    _refused(code, err, words)
    assert not started and not (tmp_path / "s.json").exists()


def test_the_service_saves_an_injection_before_its_first_frame(tmp_path: Path) -> None:
    state = tmp_path / "s.json"
    core = Supervisor((1,), 2 * J)
    config = ServiceConfig(state_path=state, fsync=False, inject_uj=3 * J)
    service = build_service(core, config, 0)
    books = load_state(state, "hardened", (1,))
    assert (books.usable, books.injected) == (5 * J, 3 * J)
    assert service.status()["injected_this_run_uj"] == 3 * J
    with pytest.raises(ValueError, match="--inject"):
        build_service(Supervisor((1,), J), ServiceConfig(listen_only=True, inject_uj=J), 0)


def test_a_listener_counts_a_supervisors_frames_and_calls_none_an_intrusion() -> None:
    """Listen-only watches a bus where a supervisor grants: frames in the supervisor's
    direction are what it came to see, counted per node; to a supervisor that sends, the same
    frame is someone else speaking in its name."""
    arbitration_id, data = Codec().encode(Intention(1, 5, 100, 0))
    frame = can.Message(arbitration_id=arbitration_id, data=data)
    listener = build_service(Supervisor((1,), J), ServiceConfig(listen_only=True), 0)
    granting = build_service(Supervisor((1,), J), ServiceConfig(), 0)
    for service in (listener, granting):
        service.on_foreign_direction(frame, 10)
    heard, judged = listener.status(), granting.status()
    assert heard["intrusions"] == 0 and heard["nodes"]["1"]["supervisor_frames"] == 1
    assert judged["intrusions"] == 1 and judged["nodes"]["1"]["supervisor_frames"] == 0
    line = supervisor_cli.listening_line("can0")(heard)
    assert line.endswith("intrusions 0, a supervisor's frames 1"), line


# -- widths ----------------------------------------------------------------------------------

ROOM = USABLE_MAX_UJ - 65_535_000  # what a node may be planned to with the default --max-grant


def _joules(uj: int) -> str:
    whole, frac = divmod(uj, J)
    return f"{whole}.{frac:06d}J"


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--target", "4400J"], ["--target 4400.000000J is above", _joules(ROOM), "4294.967295J"]),
        (["--target", _joules(ROOM + QUANTUM_UJ)], ["--target", "is above", _joules(ROOM)]),
        (
            ["--target", "4294J", "--max-grant", "1J"],
            ["--target 4294.000000J is above 4293.967295J", "--max-grant 1.000000J"],
        ),
        (["--max-node-level", "4294.967295J"], ["--max-node-level", "is above", _joules(ROOM)]),
        (["--max-grant", "66J"], ["--max-grant 66.000000J must be", "65.535000J"]),
    ],
)
def test_a_configuration_that_could_overfill_a_record_is_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]], extra: list[str], words: list[str]
) -> None:
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), *extra))
    _refused(code, err, *words)
    assert not started and not (tmp_path / "s.json").exists()


def test_the_largest_allowed_target_starts(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    argv = ["--target", _joules(ROOM), "--max-node-level", _joules(ROOM)]
    code, err = run(_supervisor("--state", str(tmp_path / "s.json"), *argv))
    assert code == 0, err
    assert len(started) == 1


def test_the_help_names_the_limits(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "1000")  # no option name broken over two lines
    with pytest.raises(SystemExit):
        main(["supervisor", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "4294.967295J (what a node's record holds) minus --max-grant" in text
    assert "65.535000J" in text
    assert "--inject ENERGY" in text and "--accept-edited-state" in text


def _service_hearing(level_uj: int) -> tuple[SupervisorService, list[dict[str, Any]]]:
    service = build_service(Supervisor((4,), 100 * J), ServiceConfig(), 0)
    service.on_message(Telemetry(4, level_uj // QUANTUM_UJ), 1)
    return service, []


def test_a_manual_grant_past_the_record_is_refused() -> None:
    service, replies = _service_hearing(USABLE_MAX_UJ - 1_999_295)  # 4292.968 J reported
    service.request_grant(4, 2 * J, replies.append)
    assert service.on_wakeup(2) == []
    assert len(replies) == 1 and "4294.967295 J, the most its record holds" in replies[0]["error"]
    assert "node 4 reports 4292.968000 J" in replies[0]["error"]
    assert service.status()["usable_uj"] == 100 * J  # nothing reserved

    service.request_grant(4, J, replies.append)  # within the record: it starts
    frames = service.on_wakeup(3)
    assert len(frames) == 1 and service.status()["reserved_uj"] == J


def test_capped_grant_keeps_a_known_level_within_the_record() -> None:
    grant: dict[str, Any] = dict(limits=Limits(), usable=10**9, granted_total=0, rate_tokens=None)
    assert capped_grant(10 * J, level=USABLE_MAX_UJ - 3 * J, **grant) == 3 * J
    assert capped_grant(10 * J, level=USABLE_MAX_UJ + J, **grant) == 0
    assert capped_grant(10 * J, level=None, **grant) == 10 * J  # unknown: the node refuses
    with pytest.raises(ValueError, match="max node level must be at most"):
        Limits(max_node_level=USABLE_MAX_UJ)


pytestmark = pytest.mark.usefixtures("both_cores")
"""Each test on the Python core and on the compiled one (tests/conftest.py)."""


# -- one keeper per record (review rv3) -------------------------------------------------------


def test_a_grant_on_the_state_file_of_a_running_supervisor_is_refused(
    tmp_path: Path, run: RunMain, procs: Procs, started: list[dict[str, Any]]
) -> None:
    """rv3: ``canergy grant --state`` beside a supervisor that keeps the same file granted from
    the same Us (1.9 J created on 5 J); each save overwrote the other's books. Now the second
    keeper is refused before it reads the file, and the file is as the first keeps it."""
    state = tmp_path / "s.json"
    bus = ["-i", "virtual", "-c", f"paths-{uuid.uuid4().hex}"]
    argv = ["supervisor", *bus, "--nodes", "1", "--no-fsync", "--state", str(state)]
    sup = procs.start("sup", python("-m", "canergy", *argv, "--initial", "5J"))
    wait(state.exists, "the supervisor's first save", 60, lambda: procs.stderr("sup"))
    books = state.read_bytes()
    code, err = run(["grant", *bus, "--node", "1", "--amount", "2J", "--state", str(state)])
    _refused(code, err, f"state file {state} is kept by another holder (pid {sup.pid}")
    _refused(*run([*argv, "--initial", "5J"]), "is kept by another holder")
    assert state.read_bytes() == books
    assert procs.stop("sup") == 0
    assert run([*argv, "--initial", "5J"]) == (0, "") and len(started) == 1  # the lock is free


def test_in_one_process_a_second_core_on_the_books_is_refused_until_the_first_is_gone(
    tmp_path: Path,
) -> None:
    """Two cores of one process on one state file (two supervisors built by a library user):
    the second is refused while the first lives, and taken once it is collected."""
    from canergy.live.atomic import RecordInUse
    from canergy.live.supervisor.build import CoreConfig, SupervisorConfig, open_core

    config = SupervisorConfig(core=CoreConfig((1,), 5 * J, state_path=tmp_path / "s.json"))
    first = open_core(config, 0)
    with pytest.raises(RecordInUse, match="is kept by another holder"):
        open_core(config, 0)
    cycle: list[Any] = [first]
    cycle.append(cycle)  # held only by a cycle: gone at the next collection
    del first, cycle
    second = open_core(config, 0)
    assert second.usable == 5 * J


# -- who may write the books' folder (review rv3, F6) -------------------------------------------


@pytest.mark.parametrize(
    ("mode", "refused"),
    [(0o777, True), (0o770, True), (0o757, True), (0o1777, False), (0o755, False), (0o700, False)],
)
def test_a_state_file_in_a_folder_others_may_write_is_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]], mode: int, refused: bool
) -> None:
    """rv3 F6: ``--state d/s.json`` with ``d`` mode 0777 started silently, and whoever can write
    ``d`` can rename an older copy over the books. Group or others may write it: refused, naming
    the folder and the fix, nothing written; sticky (as /tmp) or private: it starts."""
    folder = tmp_path / "d"
    folder.mkdir()
    folder.chmod(mode)
    state = folder / "s.json"
    code, err = run(_supervisor("--state", str(state), "--initial", "3J"))
    if refused:
        _refused(code, err, f"directory {folder} (mode {mode:04o})", f"chmod go-w {folder}")
        assert not state.exists() and not started
    else:
        assert code == 0 and state.exists() and len(started) == 1, err


def test_a_folder_above_others_may_write_is_refused_too(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    """A writer of the folder above can rename the books' folder away and put another there."""
    (tmp_path / "open").mkdir()
    (tmp_path / "open").chmod(0o777)
    (tmp_path / "open" / "d").mkdir(mode=0o700)
    state = tmp_path / "open" / "d" / "s.json"
    _refused(*run(_supervisor("--state", str(state))), f"directory {tmp_path / 'open'} (mode")
    assert not started


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a folder away needs root")
def test_a_state_file_in_another_users_folder_is_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    folder = tmp_path / "theirs"
    folder.mkdir(mode=0o755)
    os.chown(folder, 54321, -1)
    state = folder / "s.json"
    _refused(*run(_supervisor("--state", str(state))), f"directory {folder} belongs to user 54321")
    assert not started


def test_a_key_file_in_a_folder_others_may_write_is_refused(
    tmp_path: Path, run: RunMain, started: list[dict[str, Any]]
) -> None:
    """The master key (and its epochs record beside it) no one else may replace either; and
    ``canergy grant`` checks its --state as the supervisor does."""
    keys = tmp_path / "keys"
    keys.mkdir()
    assert run(["keys", "-o", str(keys / "m.key")])[0] == 0
    keys.chmod(0o777)
    state = str(tmp_path / "s.json")
    _refused(*run(_supervisor("--state", state, "--auth", str(keys / "m.key"))), f"--auth {keys}")
    grant = ["grant", "-i", "virtual", "-c", "g", "--node", "1", "--amount", "1J", "--no-fsync"]
    _refused(*run([*grant, "--state", str(keys / "s.json")]), f"chmod go-w {keys}")
    assert not started
