"""Real SocketCAN: separate processes on vcan0, can-utils around them (``pytest -m vcan``).

Run natively where vcan0 exists, or through ``scripts/uml-run`` (user-mode Linux) where the
kernel has no SocketCAN; ``scripts/test`` picks the way. These tests fail, never skip, when
vcan0 is missing: selecting them is asking for them.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import cantools
import pytest
from support.firmware_build import c_node as c_node  # the fixtures: the C node, made up to date
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import BUDGET, BUS, IFACE, c_client, client, supervisor
from support.vcan import vcan_up as vcan_up  # and vcan0 or a failure, for every test here

from canergy.ledger import ledger_from_status
from canergy.live.canopen.shared_bus import EDS

pytestmark = pytest.mark.vcan

ROOT = Path(__file__).resolve().parents[1]
DBC = ROOT / "dbc" / "canergy.dbc"


def _cansend(frame: str) -> None:
    subprocess.run(["cansend", IFACE, frame], check=True, timeout=30)


def test_processes_on_vcan0_stay_passive_through_garbage_and_kill_9(procs: Procs) -> None:
    tmp = procs.tmp
    candump = subprocess.Popen(["candump", "-l", IFACE], cwd=tmp)  # candump-<date>.log in tmp
    sup_status = tmp / "sup.json"
    supervisor(procs, "1-3", "--lost-after", "10")
    for node in (1, 2, 3):
        client(procs, node)

    def committed(node: int) -> int:
        return (
            int(status(sup_status)["nodes"][str(node)]["committed"]) if sup_status.exists() else 0
        )

    wait(lambda: all(committed(n) >= 2 for n in (1, 2, 3)), "two grants per node")

    # malformed and foreign frames: counted, never acted on
    before = status(sup_status)["decode_errors"]
    for frame in (
        "0CE00901#00",
        "0CE00901#000100",
        "0CE00F01#00",
        "0CE00101#00",
        "12345678#00",
        "701#05",
        "0CE0090A#R",
    ):
        _cansend(frame)
    wait(lambda: status(sup_status)["decode_errors"] >= before + 3, "supervisor decode errors")
    wait(lambda: status(tmp / "n1.json")["decode_errors"] >= 1, "client decode errors")

    # a client loses power hard, mid-whatever, and restarts from its NV file
    procs.stop("client2", signal.SIGKILL)
    (tmp / "n2.json").unlink()
    time.sleep(1)  # let a COMMITTED already on its way be counted
    done_before = committed(2)
    client(procs, 2)
    wait(lambda: (tmp / "n2.json").exists(), "node 2 restarting")
    wait(
        lambda: committed(2) > done_before,
        "node 2 resuming after kill -9",
        show=lambda: (
            f"supervisor's node 2: {status(sup_status)['nodes']['2']}\n"
            f"node 2: {status(tmp / 'n2.json')}\nnode 2 stderr: {procs.stderr('client2')[-2000:]}"
            f"\nsupervisor stderr: {procs.stderr('supervisor')[-2000:]}"
        ),
    )

    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")  # settles, then exits
    for node in (1, 2, 3):
        assert procs.stop(f"client{node}") == 0, procs.stderr(f"client{node}")
    candump.send_signal(signal.SIGINT)
    candump.wait(30)
    (capture,) = tmp.glob("candump-*.log")

    final = status(sup_status)
    clients = [status(tmp / f"n{n}.json") for n in (1, 2, 3)]
    books = ledger_from_status(final, clients)
    assert books.dissipated >= 0, books  # nothing generated, NV files and all
    assert final["conservation"]["holds"] and final["decode_errors"] >= 3
    assert sum(c["spent_uj"] for c in clients) > 0

    # the capture decodes with cantools and the DBC, and agrees with the supervisor's books
    db = cantools.database.load_file(str(DBC))
    commits: dict[int, set[int]] = {1: set(), 2: set(), 3: set()}
    decoded = 0
    for line in capture.read_text().splitlines():
        _, _, frame = line.split()
        ident, _, data = frame.partition("#")
        if len(ident) != 8 or data.startswith("R"):
            continue
        msg_id = int(ident, 16)
        try:
            message = db.get_message_by_frame_id(msg_id)
            message.decode(bytes.fromhex(data))
        except (KeyError, ValueError, cantools.database.DecodeError):
            continue  # the garbage injected above
        decoded += 1
        if message.name.startswith("COMMITTED_N"):
            fields = message.decode(bytes.fromhex(data))
            commits[msg_id & 0xFF].add(int(fields["TX"]))
    assert decoded > 20
    for node in (1, 2, 3):
        assert len(commits[node]) >= final["nodes"][str(node)]["committed"]

    # canergy's own decoder and auditor agree with the supervisor's books
    audit = subprocess.run(
        python("-m", "canergy", "audit", str(capture), "--initial", BUDGET, "--json"),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert audit.returncode == 0, audit.stdout + audit.stderr
    report = json.loads(audit.stdout)
    assert report["damaged_frames"] >= 4 and report["foreign_frames"] >= 2
    for node in (1, 3):  # node 2 was killed mid-run: the bus may show a commit the books wrote off
        books, seen = final["nodes"][str(node)], report["nodes"][str(node)]
        assert (seen["committed"], seen["granted_uj"]) == (
            books["committed"],
            books["committed_uj"],
        )
    decode = subprocess.run(
        python("-m", "canergy", "decode", "-", "--color", "never"),
        input=capture.read_text(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert decode.returncode == 0 and decode.stdout.count("COMMITTED") >= len(commits[1])


def test_canopen_on_vcan0_eds_master_heartbeat_loss_and_restart(procs: Procs) -> None:
    import canopen

    tmp = procs.tmp
    sup_status = tmp / "sup.json"
    supervisor(procs, "7-8", "--canopen", "--heartbeat-timeout", "3", "--status-period", "0.3")
    for node in (7, 8):
        client(procs, node, "--canopen")

    def node_status(node: int) -> dict[str, Any]:
        return status(sup_status)["nodes"][str(node)] if sup_status.exists() else {}

    wait(lambda: all(node_status(n).get("committed", 0) >= 1 for n in (7, 8)), "grants")

    # a master that knows only the EDS reads every energy object of a running emulator
    master = canopen.Network()
    master.connect(interface="socketcan", channel=IFACE)
    try:
        remote = master.add_node(canopen.RemoteNode(7, str(EDS)))
        remote.sdo.RESPONSE_TIMEOUT = 5
        names = [o.name for o in remote.object_dictionary.values() if 0x2000 <= o.index < 0x6000]
        values = {name: remote.sdo[name].raw for name in names}
    finally:
        master.disconnect()
    assert len(values) == 11 and values["Credited uJ"] >= 1_000_000

    # node 8 freezes (no telemetry; its heartbeat may go on from the kernel's CAN_BCM): the
    # supervisor marks it lost and stops granting to it
    procs.procs["client8"].send_signal(signal.SIGSTOP)
    wait(lambda: node_status(8).get("lost") is True, "node 8 marked lost", timeout_s=30)
    granted = node_status(8)["delivered_uj"]
    time.sleep(2)
    assert node_status(8)["delivered_uj"] == granted
    procs.procs["client8"].send_signal(signal.SIGCONT)
    wait(lambda: node_status(8).get("lost") is False, "node 8 back", timeout_s=60)
    # it dies and comes back from its NV file: boot-up, NMT start, grants resume
    procs.stop("client8", signal.SIGKILL)
    (tmp / "n8.json").unlink()
    time.sleep(1)  # let a COMMITTED already on its way be counted
    done = node_status(8)["committed"]
    client(procs, 8, "--canopen")
    wait(lambda: (tmp / "n8.json").exists(), "node 8 restarting")  # up, its signals handled
    wait(lambda: node_status(8)["committed"] > done, "grants to node 8 after its reboot")

    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    for node in (7, 8):
        assert procs.stop(f"client{node}") == 0, procs.stderr(f"client{node}")
    books = ledger_from_status(status(sup_status), [status(tmp / f"n{n}.json") for n in (7, 8)])
    assert books.dissipated >= 0, books


def test_a_node_whose_nv_file_is_deleted_rejoins_without_creating_energy(procs: Procs) -> None:
    """Issue 13: a node started without its record used to be paid back all of Gs."""
    tmp = procs.tmp
    sup_status, node_status = tmp / "sup.json", tmp / "n1.json"
    supervisor(procs, "1", "--lost-after", "10")
    client(procs, 1)

    def node_books() -> dict[str, Any]:
        return dict(status(sup_status)["nodes"]["1"]) if sup_status.exists() else {}

    wait(lambda: node_books().get("committed", 0) >= 2, "two grants")
    procs.stop("client1", signal.SIGKILL)
    before = status(node_status)
    (tmp / "n1.nv").unlink()
    node_status.unlink()
    client(procs, 1)
    assert node_books()["admitted"] == 1  # its first start had no file either
    wait(lambda: node_books()["admitted"] >= 2, "node 1 admitted again")
    done = node_books()["committed"]
    wait(lambda: node_books()["committed"] >= done + 1, "a grant after admission")

    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert procs.stop("client1") == 0, procs.stderr("client1")
    final, after = status(sup_status), status(node_status)
    assert after["joins"] == 1 and not after["joining"]
    books = final["nodes"]["1"]
    released = books["delivered_uj"] - books["returns_credited_uj"]
    lives = before["usable_uj"] + before["drawn_uj"] + after["usable_uj"] + after["drawn_uj"]
    assert lives <= released, (lives, released)
    assert ledger_from_status(final, [after]).dissipated >= 0


# The C node (firmware/ports/linux): the same process model, flags, NV file and status file as
# firmware_model --node, so the tests above carry over with the binary in its place.
def test_c_nodes_on_vcan0_stay_passive_through_garbage_and_kill_9(
    procs: Procs, c_node: Path
) -> None:
    tmp = procs.tmp
    candump = subprocess.Popen(["candump", "-l", IFACE], cwd=tmp)
    sup_status = tmp / "sup.json"
    supervisor(procs, "1-3", "--lost-after", "10")
    for node in (1, 2, 3):
        c_client(procs, c_node, node, "--return-above", "0.8J")

    def committed(node: int) -> int:
        return (
            int(status(sup_status)["nodes"][str(node)]["committed"]) if sup_status.exists() else 0
        )

    wait(lambda: all(committed(n) >= 2 for n in (1, 2, 3)), "two grants per C node")
    before = status(sup_status)["decode_errors"]
    for frame in (
        "0CE00901#00",  # ACK with a wrong length, to the supervisor
        "0CE00101#00",  # INTENTION to node 1 with a wrong length
        "0CE00201#0011",  # COMMIT to node 1, wrong length
        "0CE00301#R",  # remote frame for node 1
        "0CE00101#FF0100E8030000FF",  # INTENTION to node 1, bad CRC
        "12345678#00",
        "701#05",
    ):
        _cansend(frame)
    wait(lambda: status(sup_status)["decode_errors"] >= before + 1, "supervisor decode errors")
    wait(lambda: status(tmp / "n1.json")["decode_errors"] >= 4, "C node decode errors")
    reasons = status(tmp / "n1.json")["decode_error_reasons"]
    assert reasons.get("remote frame", 0) >= 1 and reasons.get("CRC mismatch", 0) >= 1, reasons

    procs.stop("client2", signal.SIGKILL)  # power lost at any instant: NV holds the books
    (tmp / "n2.json").unlink()
    time.sleep(1)
    done_before = committed(2)
    c_client(procs, c_node, 2, "--return-above", "0.8J")
    wait(lambda: (tmp / "n2.json").exists(), "C node 2 restarting")
    wait(lambda: committed(2) > done_before, "C node 2 resuming after kill -9")
    restarted = status(tmp / "n2.json")
    assert restarted["joins"] == 0 and restarted["nv_fallbacks"] == 0, restarted

    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    for node in (1, 2, 3):
        assert procs.stop(f"client{node}") == 0, procs.stderr(f"client{node}")
    candump.send_signal(signal.SIGINT)
    candump.wait(30)
    (capture,) = tmp.glob("candump-*.log")

    final = status(sup_status)
    clients = [status(tmp / f"n{n}.json") for n in (1, 2, 3)]
    assert all(c["implementation"] == "c" for c in clients)
    books = ledger_from_status(final, clients)
    assert books.dissipated >= 0, books  # nothing created
    assert final["conservation"]["holds"]
    assert sum(c["spent_uj"] for c in clients) > 0
    assert sum(c["returned_uj"] for c in clients) > 0  # --return-above gave some back
    for c in clients:
        assert c["credited_uj"] <= final["nodes"][str(c["node"])]["delivered_uj"], c

    audit = subprocess.run(
        python("-m", "canergy", "audit", str(capture), "--initial", BUDGET, "--json"),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert audit.returncode == 0, audit.stdout + audit.stderr  # passive: nothing created
    report = json.loads(audit.stdout)
    assert report["damaged_frames"] >= 4 and report["foreign_frames"] >= 2
    for node in (1, 3):
        books_n, seen = final["nodes"][str(node)], report["nodes"][str(node)]
        assert (seen["committed"], seen["granted_uj"]) == (
            books_n["committed"],
            books_n["committed_uj"],
        )


def test_a_node_moves_between_firmware_model_and_the_c_node_with_its_nv_file(
    procs: Procs, c_node: Path
) -> None:
    """Python -> C -> Python on one NV file: the books carry over, nothing replays."""
    tmp = procs.tmp
    sup_status, node_status = tmp / "sup.json", tmp / "n4.json"
    supervisor(procs, "4", "--lost-after", "10")

    def books() -> dict[str, Any]:
        return dict(status(sup_status)["nodes"]["4"]) if sup_status.exists() else {}

    lives: list[dict[str, Any]] = []
    for i, implementation in enumerate(("python", "c", "python")):
        node_status.unlink(missing_ok=True)
        done = int(books().get("committed", 0))
        if implementation == "c":
            c_client(procs, c_node, 4)
        else:
            client(procs, 4)
        wait(
            lambda done=done: books().get("committed", 0) >= done + 2,  # type: ignore[misc]
            f"two grants in life {i} ({implementation})",
        )
        assert procs.stop("client4") == 0, procs.stderr("client4")
        life = status(node_status)
        assert life["joins"] == (1 if i == 0 else 0), life  # only the blank file joins
        assert life["nv_fallbacks"] == 0 and life["nv_writes"] > 0, life
        if lives:
            prev = lives[-1]  # nothing lost, nothing replayed across the move
            assert life["credited_uj"] > prev["credited_uj"], (prev, life)
            assert life["spent_uj"] >= prev["spent_uj"], (prev, life)
            assert life["last_tx"] > prev["last_tx"], (prev, life)
        lives.append(life)
    nv = (tmp / "n4.nv").read_bytes()
    assert len(nv) >= 80

    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    final = status(sup_status)
    last = lives[-1]
    node_books = final["nodes"]["4"]
    # every COMMIT the supervisor counted was credited, none twice, across three processes
    assert node_books["committed_uj"] <= last["credited_uj"] <= node_books["delivered_uj"], (
        last,
        node_books,
    )
    assert ledger_from_status(final, [last]).dissipated >= 0


def test_the_c_node_refuses_an_nv_path_that_is_not_an_nv_file(tmp_path: Path, c_node: Path) -> None:
    """The first record would overwrite it (as python -m firmware_model refuses too)."""
    notes = tmp_path / "notes.txt"
    notes.write_text("not a record")
    run = subprocess.run(
        [str(c_node), "--node", "1", *BUS, "--nv", str(notes)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2 and "is not an NV file" in run.stderr, run.stderr
    assert notes.read_text() == "not a record"


def _link(state: str) -> None:
    subprocess.run(["ip", "link", "set", IFACE, state], check=True, timeout=30)


def test_vcan0_down_is_in_the_status_and_grants_resume_when_it_is_back(procs: Procs) -> None:
    """``ip link set vcan0 down`` for 4 s under a supervisor and a node: the supervisor's status
    says ``bus_state: down`` (socketcan reports no state of its own; python-can's default said
    ``active`` throughout), and once the link is back it says so and grants go on."""
    sup_status = procs.tmp / "sup.json"
    supervisor(procs, "1", "--lost-after", "10")
    client(procs, 1)

    def committed() -> int:
        return int(status(sup_status)["nodes"]["1"]["committed"]) if sup_status.exists() else 0

    wait(lambda: committed() >= 1, "a first grant")
    assert status(sup_status)["bus_state"] == "unknown"
    _link("down")
    try:
        wait(lambda: status(sup_status)["bus_state"] == "down", "the link seen down", 60)
        time.sleep(4)
    finally:
        _link("up")
    wait(lambda: status(sup_status)["bus_state"] == "unknown", "the link seen back", 60)
    before = committed()
    wait(lambda: committed() > before, "a grant after the link came back")
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert procs.stop("client1") == 0, procs.stderr("client1")
    books = ledger_from_status(status(sup_status), [status(procs.tmp / "n1.json")])
    assert books.dissipated >= 0, books
