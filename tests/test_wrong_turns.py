"""The first wrong turns of issue 44 answered where they are taken.

python-can's ``virtual`` interface connects only the buses of one process: a supervisor and a
node emulator started in two processes on ``-i virtual`` never hear each other. Each says why
within its first status period, on stderr and in its status (``bus_note``), and ``canergy
grant`` tells "no supervisor on that socket" from "the supervisor answered: no node took the
grant", naming the node's state.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from support.procs import Procs, python, status, wait

from canergy.live.runtime import BusRuntime
from canergy.live.transports.virtual_alone import ALONE_AFTER_US
from canergy.messages import Direction

WHY = "it connects only buses of one process"


class _Quiet:
    def on_message(self, msg, now):  # type: ignore[no-untyped-def]
        return ()

    def next_wakeup(self) -> None:
        return None

    def on_wakeup(self, now):  # type: ignore[no-untyped-def]
        return ()


def _note_after_start(company: bool, capsys: pytest.CaptureFixture[str]) -> str | None:
    channel = f"alone-{uuid.uuid4().hex}"
    clock = [0]
    bus = can.Bus(interface="virtual", channel=channel)
    other = can.Bus(interface="virtual", channel=channel) if company else None
    try:
        runtime = BusRuntime(
            bus, _Quiet(), receives=Direction.TO_SUPERVISOR, clock=lambda: clock[0]
        )  # type: ignore[arg-type]
        clock[0] = ALONE_AFTER_US - 1
        runtime.poll(0)
        assert runtime.counters.bus_note is None  # not before it looked
        clock[0] = ALONE_AFTER_US
        runtime.poll(0)
        note = runtime.counters.bus_note
        assert ("bus_note" in runtime.counters.as_json()) is (note is not None)
        assert (WHY in capsys.readouterr().err) is (note is not None)
        return note
    finally:
        bus.shutdown()
        if other is not None:
            other.shutdown()


def test_a_virtual_bus_alone_in_its_process_says_why(capsys: pytest.CaptureFixture[str]) -> None:
    note = _note_after_start(company=False, capsys=capsys)
    assert note is not None and WHY in note and "scripts/uml-run" in note


def test_a_virtual_bus_shared_within_the_process_says_nothing(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert _note_after_start(company=True, capsys=capsys) is None


@pytest.fixture(scope="module")
def two_processes(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Procs, Path]]:
    """A supervisor and a node emulator, each in its own process, on one virtual channel."""
    tmp = tmp_path_factory.mktemp("virtual")
    bus = ["-i", "virtual", "-c", f"lab-{uuid.uuid4().hex[:8]}"]
    procs = Procs(tmp)
    supervisor = ["supervisor", *bus, "--nodes", "1", "--initial", "10J", "--target", "1J"]
    supervisor += ["--state", "sup.json", "--status-file", "status.json", "--control", "c.sock"]
    procs.start("supervisor", python("-m", "canergy", *supervisor, "--status-period", "1s"))
    node = ["--node", "1", *bus, "--nv", "nv/", "--status-file", "node.json"]
    procs.start("node", python("-m", "firmware_model", *node, "--status-period", "1s"))
    try:
        yield procs, tmp
        for name in ("supervisor", "node"):
            assert procs.stop(name, signal.SIGINT) == 0, procs.stderr(name)
    finally:
        procs.close()


def test_virtual_across_two_processes_says_why(two_processes: tuple[Procs, Path]) -> None:
    procs, tmp = two_processes
    for name, path in (("supervisor", "status.json"), ("node", "node.json")):
        wait(lambda path=path: "bus_note" in status(tmp / path), f"{name}'s bus_note", 30)
        assert WHY in status(tmp / path)["bus_note"]
        wait(lambda name=name: WHY in procs.stderr(name), f"{name}'s explanation on stderr", 30)
    # the first status that has the note is the one written a status period after the start
    assert status(tmp / "status.json")["uptime_s"] < 2.5


def _grant(control: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    argv = [sys.executable, "-m", "canergy", "grant", "--control", str(control)]
    argv += ["--node", "1", "--amount", "0.5J", "--timeout", "1s"]
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=60)


def test_grant_with_no_supervisor_on_the_socket(tmp_path: Path) -> None:
    missing = _grant(tmp_path / "nobody.sock", tmp_path)
    (tmp_path / "stale.sock").touch()  # a file where no supervisor listens
    stale = _grant(tmp_path / "stale.sock", tmp_path)
    for done in (missing, stale):
        assert done.returncode == 2, done.stderr
        assert "no supervisor listens on" in done.stderr and "took the request" not in done.stderr


def test_grant_that_no_node_took_names_the_nodes_state(two_processes: tuple[Procs, Path]) -> None:
    _, tmp = two_processes
    wait(lambda: (tmp / "c.sock").exists(), "the control socket", 30)
    done = _grant(tmp / "c.sock", tmp)
    assert done.returncode == 1, done.stderr
    assert "took the request, but node 1 took no grant within --timeout 1 s" in done.stderr
    assert "it is lost" in done.stderr and "transaction state is IDLE" in done.stderr
    assert WHY in done.stderr  # and why nothing is heard
    assert "no supervisor listens" not in done.stderr
