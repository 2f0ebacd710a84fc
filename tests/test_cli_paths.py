"""Paths at the command line (issue 13): readers never create the file they are asked to read,
and ``python -m firmware_model`` checks every output before it starts; a bad path is one line
naming it, exit status 2, and nothing is left behind."""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from unittest import mock

import can
import pytest

import firmware_model.__main__ as firmware
from canergy.cli import main
from canergy.inspect.captures import TEXT_SUFFIXES, CaptureError, read_file

DATA = Path(__file__).parent / "data"
SUFFIXES = sorted({*TEXT_SUFFIXES, *can.io.MESSAGE_READERS})


def _one_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("command", ["audit", "decode"])
@pytest.mark.parametrize("suffix", SUFFIXES)
def test_a_missing_capture_is_an_error_and_is_not_created(
    command: str, suffix: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / f"typo{suffix}"
    assert main([command, str(path)]) == 2
    line = _one_error(capsys.readouterr().err)
    assert f"canergy {command}: error: {path}: no such file" == line
    assert list(tmp_path.iterdir()) == []


def test_audit_of_a_typo_db_creates_no_database(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["audit", "typo.db"]) == 2
    assert "typo.db: no such file" in _one_error(capsys.readouterr().err)
    assert not Path("typo.db").exists()


@pytest.mark.parametrize("command", ["audit", "decode"])
@pytest.mark.parametrize("name", ["folder", "folder.db", "folder.asc", "folder.log"])
def test_a_directory_is_not_a_capture(
    command: str, name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / name).mkdir()
    assert main([command, str(tmp_path / name)]) == 2
    assert "is a directory" in _one_error(capsys.readouterr().err)
    assert [p.name for p in tmp_path.iterdir()] == [name]
    assert list((tmp_path / name).iterdir()) == []


def test_the_check_comes_at_the_call_not_at_the_first_frame(tmp_path: Path) -> None:
    with pytest.raises(CaptureError, match="no such file"):
        read_file(tmp_path / "missing.asc", lambda *a: None)
    assert list(tmp_path.iterdir()) == []


def test_candump_text_through_a_pipe_is_still_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``canergy decode <(candump -L vcan0)``: the shell passes a pipe's name."""
    fifo = tmp_path / "live"
    os.mkfifo(fifo)
    text = (DATA / "two-nodes.log").read_text()

    def write() -> None:
        with open(fifo, "w") as f:
            f.write(text)

    writer = threading.Thread(target=write)
    writer.start()
    try:
        assert main(["decode", "--color", "never", str(fifo)]) == 0
    finally:
        writer.join(timeout=10)
    assert capsys.readouterr().out == (DATA / "two-nodes.decoded").read_text()


def test_a_binary_format_must_be_a_regular_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    fifo = tmp_path / "live.blf"
    os.mkfifo(fifo)  # opening it for reading blocks until a writer comes: refused before
    codes: list[int] = []
    audit = threading.Thread(target=lambda: codes.append(main(["audit", str(fifo)])))
    audit.start()
    audit.join(timeout=10)
    if audit.is_alive():  # blocked in open(): a writer that closes at once lets it go
        with open(fifo, "wb"):
            pass
        audit.join()
    assert codes == [2]
    assert "not a regular file" in _one_error(capsys.readouterr().err)


def test_an_unreadable_capture_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "secret.log"
    path.write_text("")
    path.chmod(0)
    real_access = os.access
    if os.geteuid() == 0:  # root reads every file: let access() answer as for another user
        monkeypatch.setattr(
            os, "access", lambda p, mode: False if Path(p) == path else real_access(p, mode)
        )
    assert main(["decode", str(path)]) == 2
    assert "not readable" in _one_error(capsys.readouterr().err)


# --- python -m firmware_model -------------------------------------------------------------------


class _Served(Exception):
    """The emulator got past its start-up checks and would now run."""


@pytest.fixture
def emulator(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[None]:
    """Run ``firmware_model.main`` here: it stops where it would serve, and its signal handlers
    are put back afterwards."""

    def serve(*args: object) -> None:
        raise _Served

    monkeypatch.setattr(firmware, "_serve", serve)
    monkeypatch.chdir(tmp_path)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1)}
    try:
        yield
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        firmware.main([*argv, "-i", "virtual", "--no-fsync"])
    assert exc.value.code == 2
    return _one_error(capsys.readouterr().err)


def _tree(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.usefixtures("emulator")
@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--node", "1", "--nv", "missing/n.nv"], "cannot write --nv missing/n.nv: no directory"),
        (
            ["--nodes", "1-2", "--nv", "missing/nodes"],
            "cannot write --nv missing/nodes: no directory missing",
        ),
        (
            ["--node", "1", "--nv", "n.nv", "--status-file", "missing/s.json"],
            "cannot write --status-file missing/s.json: no directory",
        ),
        (
            ["--node", "1", "--nv", "n.nv", "--status-file", "n.nv"],
            "--nv n.nv and --status-file n.nv name the same file",
        ),
        (
            ["--node", "1", "--nv", "n.nv", "--status-file", "./sub/../n.nv"],
            "name the same file",
        ),
        (
            ["--nodes", "1-2", "--nv", "sub", "--status-file", "sub/node-002.nv"],
            "--nv sub/node-002.nv and --status-file sub/node-002.nv name the same file",
        ),
        (
            ["--node", "1", "--nv", "n.nv", "--power-profile", "p.csv", "--status-file", "p.csv"],
            "--status-file p.csv and --power-profile p.csv name the same file",
        ),
        (["--node", "1", "--nv", "p.csv", "--power-profile", "p.csv"], "name the same file"),
        (
            ["--node", "1", "--nv", "n.nv", "--status-file", "./k.key", "--auth", "k.key"],
            "--status-file k.key and --auth k.key name the same file",
        ),
        (["--node", "1", "--nv", "k.key", "--auth", "k.key"], "--nv k.key and --auth k.key"),
        (["--nodes", "1-2", "--nv", "p.csv"], "--nv p.csv: not a directory"),
        (["--node", "1", "--nv", "n.nv", "--power-profile", "none.csv"], "--power-profile"),
        (["--node", "1", "--nv", "n.nv", "--power-profile", "inf.csv"], "must be finite"),
        (["--node", "1", "--nv", "p.csv"], "--nv p.csv: 19 bytes is not an NV file"),
        (["--nodes", "1-2", "--nv", "old"], "--nv old/node-001.nv: 5 bytes is not an NV file"),
    ],
)
def test_firmware_paths_are_checked_before_it_starts(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "node-001.nv").write_text("notes")  # not written by a node
    (tmp_path / "p.csv").write_text("time_s,watts\n0,0.5\n")
    (tmp_path / "inf.csv").write_text("time_s,watts\n0,0.5\n1,inf\n")
    before = _tree(tmp_path)
    line = _refused(argv, capsys)
    assert line.startswith("python -m firmware_model: error: ") and message in line, line
    assert _tree(tmp_path) == before


@pytest.mark.usefixtures("emulator")
def test_the_same_file_through_a_link_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    os.symlink(tmp_path / "n.nv", tmp_path / "link.nv")
    line = _refused(["--node", "1", "--nv", "n.nv", "--status-file", "link.nv"], capsys)
    assert "name the same file" in line


@pytest.mark.usefixtures("emulator")
def test_a_bus_that_cannot_open_leaves_no_nv_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # no such interface where the kernel has SocketCAN, no SocketCAN where it has not
    argv = ["--nodes", "1-2", "--nv", "nodes", "-i", "socketcan", "-c", "no-such-canergy-if"]
    with pytest.raises(SystemExit) as exc:
        firmware.main(argv)
    assert exc.value.code == 2
    assert "cannot open the CAN bus" in _one_error(capsys.readouterr().err)
    assert not (tmp_path / "nodes").exists()


NODE_FILES = ("nodes", "nodes/node-001.nv", "nodes/node-002.nv")


@pytest.mark.usefixtures("emulator")
@pytest.mark.parametrize(
    ("argv", "made"),
    [
        (["--node", "1", "--nv", "n.nv", "--status-file", "s.json"], ["n.nv"]),
        (["--nodes", "1-2", "--nv", "nodes", "--status-file", "nodes.json"], [*NODE_FILES]),
        (["--nodes", "1-2", "--nv", "nodes"], [*NODE_FILES]),
    ],
)
def test_good_paths_start(argv: list[str], made: list[str], tmp_path: Path) -> None:
    """Each node's NV file is there (empty: a new record) once it starts, locked while it runs
    (``tests/test_record_keepers.py``), as the C node's; nothing else is written before the
    loop runs."""
    with pytest.raises(_Served):
        firmware.main([*argv, "-i", "virtual", "--no-fsync"])
    assert _tree(tmp_path) == made


# --- outputs of long commands are checked before the work ---------------------------------------


def test_bench_checks_its_json_output_first(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with mock.patch("canergy.bench.run.run", side_effect=AssertionError("benchmarked")):
        assert main(["bench", "--quick", "--json", str(tmp_path / "missing" / "b.json")]) == 2
    assert "--json" in _one_error(capsys.readouterr().err)


@pytest.mark.parametrize("command", ["simulate", "sweep"])
@pytest.mark.parametrize("out", ["file.txt", "file.txt/deeper"])
def test_simulations_check_their_output_directory_first(
    command: str, out: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "file.txt").write_text("not a directory")
    with (
        mock.patch("canergy.cli.simulate.simulate", side_effect=AssertionError("simulated")),
        mock.patch("canergy.sim.sweep.sweep", side_effect=AssertionError("swept")),
    ):
        assert main([command, "--out", str(tmp_path / out), "--duration", "1"]) == 2
    line = _one_error(capsys.readouterr().err)
    assert "cannot write --out" in line and "not a directory" in line
    assert _tree(tmp_path) == ["file.txt"]


@pytest.mark.parametrize("command", ["simulate", "sweep"])
def test_a_new_output_directory_may_be_nested(command: str, tmp_path: Path) -> None:
    with (
        mock.patch("canergy.cli.simulate.simulate", side_effect=_Served),
        mock.patch("canergy.sim.sweep.sweep", side_effect=_Served),
        pytest.raises(_Served),
    ):
        main([command, "--out", str(tmp_path / "sweeps" / "paper"), "--duration", "1"])


def test_a_long_check_reports_progress_on_a_terminal_unless_told_not_to(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 31, item 8: the README's 100 s and 12 min checks printed nothing unless one knew
    --progress."""
    import io

    from canergy.cli import build_parser
    from canergy.cli.check import _progress, _report_progress

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    def shown(*flags: str) -> bool:
        return _progress(build_parser().parse_args(["check", *flags])) is _report_progress

    monkeypatch.setattr(sys, "stderr", Terminal())
    assert shown() and shown("--progress") and not shown("--no-progress")
    monkeypatch.setattr(sys, "stderr", io.StringIO())  # a pipe or a file: quiet by default
    assert not shown() and shown("--progress")


@pytest.mark.usefixtures("emulator")
@pytest.mark.parametrize(
    "argv", [["--node", "1", "--nv", "d/n.nv"], ["--nodes", "1-2", "--nv", "d/nodes"]]
)
def test_an_nv_record_in_a_folder_others_may_write_is_refused(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rv3 F6: whoever can write the folder of a node's NV record can roll it back. The emulator
    refuses it, naming the folder and the fix, and writes nothing; sticky (as /tmp) it starts."""
    (tmp_path / "d").mkdir()
    (tmp_path / "d").chmod(0o777)
    line = _refused(argv, capsys)
    folder = tmp_path / "d"
    assert f"directory {folder} (mode 0777)" in line and f"chmod go-w {folder}" in line, line
    assert _tree(tmp_path) == ["d"]
    (tmp_path / "d").chmod(0o1777)
    with pytest.raises(_Served):
        firmware.main([*argv, "-i", "virtual", "--no-fsync"])


@pytest.mark.usefixtures("emulator")
def test_the_nodes_folder_it_makes_is_private_whatever_the_umask(tmp_path: Path) -> None:
    """Under a 002 umask (Ubuntu's for users) ``--nv nodes`` was made 0775, and the next start
    refused its own folder as others may write it (rv3 F6's check)."""
    old = os.umask(0o002)
    try:
        for _ in range(2):  # the second start takes the folder the first made
            with pytest.raises(_Served):
                firmware.main(["--nodes", "1-2", "--nv", "nodes", "-i", "virtual", "--no-fsync"])
    finally:
        os.umask(old)
    assert (tmp_path / "nodes").stat().st_mode & 0o777 == 0o755
