"""Security on real SocketCAN (``pytest -m vcan``): separate processes on vcan0, can-utils as the
attacker. Classic mode reports a spoofer and a second supervisor within a second; authenticated
mode (CAN FD) moves nothing for forged frames or for a capture replayed with canplayer after a
node's NV record was wiped, and counts them.
"""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from support.procs import Procs, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import BUS, IFACE, TIMEOUT, client, supervisor, vcan_up

from canergy.codec import Codec
from canergy.ledger import ledger_from_status
from canergy.messages import Commit, Intention, Return

pytestmark = pytest.mark.vcan
__all__ = ["vcan_up"]

CODEC = Codec()


def _mtu() -> int:
    return int(Path(f"/sys/class/net/{IFACE}/mtu").read_text())


def _frame(msg: Any) -> str:
    """A cansend frame for ``msg``, built with the public codec (no key)."""
    arbitration_id, data = CODEC.encode(msg)
    return f"{arbitration_id:08X}#{data.hex().upper()}"


def _cansend(frame: str) -> int:
    """Send one frame; when it left (monotonic µs)."""
    sent = time.monotonic_ns() // 1000
    subprocess.run(["cansend", IFACE, frame], check=True, timeout=30)
    return sent


def _intrusions(path: Path) -> dict[str, Any]:
    return dict(status(path)["intrusion_report"]) if path.exists() else {"total": 0}


def test_a_spoofer_and_a_second_supervisor_are_reported_within_a_second(procs: Procs) -> None:
    tmp = procs.tmp
    sup_status = tmp / "sup.json"
    supervisor(procs, "1", "--status-period", "0.2")
    client(procs, 1)
    wait(
        lambda: sup_status.exists() and status(sup_status)["nodes"]["1"]["committed"] >= 1,
        "a first grant",
    )
    # a spoofer speaking for node 1: the node reports it
    sent = _cansend(_frame(Return(1, 500, 65535)))
    wait(lambda: status(tmp / "n1.json")["intrusions"] >= 1, "the node reporting the spoof")
    first = status(tmp / "n1.json")["intrusion_report"]["first_at_us"]
    assert first - sent < 1_000_000
    # a frame only the supervisor sends, as a second supervisor's first one: reported in time
    sent = _cansend(_frame(Intention(1, 900, 1, 0)))
    wait(lambda: _intrusions(sup_status)["total"] >= 1, "the supervisor reporting it")
    assert _intrusions(sup_status)["first_at_us"] - sent < 1_000_000
    # and a real second supervisor on the same id is reported too
    second = tmp / "second"
    second.mkdir()
    procs.start("second", _second_supervisor(second))
    wait(
        lambda: (second / "sup.json").exists() and status(second / "sup.json")["frames_sent"] > 0,
        "the second supervisor sending",
    )

    def foreign_supervisor_frames() -> int:
        events = _intrusions(sup_status).get("recent", [])
        return sum(e["kind"] == "a frame only this supervisor sends" for e in events)

    wait(lambda: foreign_supervisor_frames() >= 2, "the supervisor reporting the other")
    assert procs.stop("second") == 0, procs.stderr("second")
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert procs.stop("client1") == 0, procs.stderr("client1")


def _second_supervisor(tmp: Path) -> list[str]:
    import sys

    return [
        sys.executable,
        *("-m", "canergy", "supervisor", *BUS, "--nodes", "1", "--initial", "5J"),
        *("--target", "2J", "--max-grant", "0.5J", "--state", str(tmp / "state.json")),
        *("--status-file", str(tmp / "sup.json"), *TIMEOUT),
    ]


def test_authenticated_fd_moves_nothing_for_forgeries_or_a_replayed_capture(procs: Procs) -> None:
    assert _mtu() >= 72, f"CAN FD needs {IFACE} at mtu 72: ip link set {IFACE} mtu 72 (down)"
    tmp = procs.tmp
    subprocess.run([*_canergy(), "keys", "-o", str(tmp / "m.key")], check=True, timeout=60, cwd=tmp)
    subprocess.run(
        [
            *_canergy(),
            "keys",
            "--master",
            str(tmp / "m.key"),
            "--nodes",
            "1",
            "-o",
            str(tmp / "n1.key"),
        ],
        check=True,
        timeout=60,
    )
    candump = subprocess.Popen(["candump", "-l", IFACE], cwd=tmp)
    sup_status = tmp / "sup.json"
    supervisor(procs, "1", "--fd", "--auth", str(tmp / "m.key"), "--status-period", "0.2")
    client(procs, 1, "--fd", "--auth", str(tmp / "n1.key"))
    wait(
        lambda: sup_status.exists() and status(sup_status)["nodes"]["1"]["committed"] >= 3,
        "authenticated grants",
    )
    candump.send_signal(signal.SIGINT)
    candump.wait(30)
    (capture,) = tmp.glob("candump-*.log")
    # forgeries with the public codec: plain frames, and FD-shaped ones with a made-up MAC
    tx = status(sup_status)["nodes"]["1"]["open_tx"] or 0
    for msg in (Commit(1, tx + 1, 65535), Intention(1, tx + 1, 65535, 0)):
        _cansend(_frame(msg))
        arbitration_id, data = CODEC.encode(msg)
        _cansend(f"{arbitration_id:08X}##1{(data + bytes(20 - len(data))).hex().upper()}")
    # the node loses its NV record and rejoins; then the whole capture is replayed
    procs.stop("client1", signal.SIGKILL)
    (tmp / "n1.nv").unlink()
    (tmp / "n1.json").unlink()
    client(procs, 1, "--fd", "--auth", str(tmp / "n1.key"))
    wait(
        lambda: (tmp / "n1.json").exists() and not status(tmp / "n1.json")["joining"],
        "node 1 admitted again",
    )
    before = status(tmp / "n1.json")["credited_uj"]
    subprocess.run(["canplayer", "-I", str(capture), "-t"], check=True, timeout=120)
    wait(lambda: status(tmp / "n1.json")["intrusions"] >= 3, "the node counting the replay")
    time.sleep(1)
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert procs.stop("client1") == 0, procs.stderr("client1")
    final, node = status(sup_status), status(tmp / "n1.json")
    assert sum(node["intrusion_report"]["by_node"].values()) >= 3
    # the replay credited nothing beyond what the supervisor granted since the rejoin
    assert node["credited_uj"] - before <= final["nodes"]["1"]["delivered_uj"]
    books = ledger_from_status(final, [node])
    assert books.passive, books


def _canergy() -> list[str]:
    import sys

    return [sys.executable, "-m", "canergy"]
