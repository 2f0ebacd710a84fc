"""The C node (firmware/build/canergy-node) in authenticated mode on real SocketCAN
(``pytest -m vcan``): the Python supervisor with the master key grants to it, CAN FD and classic
layout; forged frames built with the public codec (no key) move nothing and are counted by the
C node; a frame in its name is reported as an intrusion; the ledger closes.
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import pytest
from support.firmware_build import c_node as c_node
from support.procs import Procs, status, wait
from support.procs import procs as procs  # the fixtures
from support.vcan import IFACE, c_client, keys, supervisor, vcan_up

from canergy.codec import Codec
from canergy.ledger import ledger_from_status
from canergy.messages import Commit, Intention, Return

pytestmark = pytest.mark.vcan
__all__ = ["vcan_up"]

CODEC = Codec()


def _cansend(frame: str) -> None:
    subprocess.run(["cansend", IFACE, frame], check=True, timeout=30)


def _plain(msg: Any) -> str:
    """``msg`` as cansend's argument, built with the public codec and no key."""
    arbitration_id, data = CODEC.encode(msg)
    return f"{arbitration_id:08X}#{data.hex().upper()}"


def _forgeries(fd: bool, tx: int) -> list[str]:
    """Frames a device without the key can make for node 1: a plain COMMIT (no MAC), one with a
    made-up MAC in the layout's shape, and an INTENTION likewise."""
    frames = []
    for msg in (Commit(1, tx + 1, 65535), Intention(1, tx + 1, 65535, 0)):
        arbitration_id, data = CODEC.encode(msg)
        frames.append(_plain(msg))
        if fd:  # data || padding || FV || MAC, all made up
            body = data + bytes(20 - len(data) - 12) + (tx + 1).to_bytes(4, "big") + bytes(8)
            frames.append(f"{arbitration_id:08X}##1{body.hex().upper()}")
        else:  # the data frame, then a MAC frame with a made-up MAC
            mac_frame = bytes([msg.TYPE]) + bytes(2) + bytes.fromhex("0102030405")
            frames += [_plain(msg), f"{CODEC.id_base | 1:08X}#{mac_frame.hex().upper()}"]
    return frames


@pytest.mark.parametrize("fd", [True, False], ids=["fd", "classic"])
def test_c_auth_node_is_granted_by_the_python_supervisor_and_refuses_forgeries(
    procs: Procs, c_node: Path, fd: bool
) -> None:
    if fd:
        mtu = int(Path(f"/sys/class/net/{IFACE}/mtu").read_text())
        assert mtu >= 72, f"CAN FD needs {IFACE} at mtu 72: ip link set {IFACE} mtu 72"
    tmp = procs.tmp
    master, node_key = keys(tmp)
    fd_flag = ["--fd"] if fd else []
    sup_status, node_status = tmp / "sup.json", tmp / "n1.json"
    supervisor(procs, "1", *fd_flag, "--auth", str(master), "--status-period", "0.2")
    c_client(procs, c_node, 1, *fd_flag, "--auth", str(node_key), "--return-above", "0.8J")

    def committed() -> int:
        return int(status(sup_status)["nodes"]["1"]["committed"]) if sup_status.exists() else 0

    wait(lambda: committed() >= 3, "three authenticated grants to the C node")
    node = status(node_status)
    assert node["implementation"] == "c" and node["joins"] == 1, node
    assert node["auth_failures"] == {} and node["intrusions"] == 0, node
    sup = status(sup_status)
    assert not sup.get("auth_failures"), sup  # every frame of the C node verified in Python

    # forgeries with the public codec: refused and counted by the C node, nothing credited
    tx = int(node["last_tx"]) & 0xFFFF
    for frame in _forgeries(fd, tx):
        _cansend(frame)
    _cansend(_plain(Return(1, 500, 65535)))  # someone speaking in node 1's name

    def refused() -> int:
        return sum(status(node_status)["auth_failures"].values())

    wait(lambda: refused() >= 2, "the C node counting the forgeries")
    wait(lambda: status(node_status)["intrusions"] >= refused() + 1, "the spoofed RETURN")
    node = status(node_status)
    reasons = set(node["auth_failures"])
    if fd:
        assert {"frame without a MAC", "MAC BAD"} <= reasons, node["auth_failures"]
    else:
        assert "MAC BAD" in reasons or "MAC frame without its message" in reasons, reasons
    kinds = {e["kind"] for e in node["intrusion_report"]["recent"]}
    assert "a frame in its name" in kinds, node["intrusion_report"]
    # grants go on after the forgeries
    done = committed()
    wait(lambda: committed() >= done + 2, "grants after the forgeries")

    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    assert procs.stop("client1") == 0, procs.stderr("client1")
    final, node = status(sup_status), status(node_status)
    # nothing forged was credited (a forged COMMIT alone was 65.535 J): the node holds no more
    # than the supervisor delivered
    assert node["credited_uj"] <= final["nodes"]["1"]["delivered_uj"], (node, final)
    assert node["spent_uj"] > 0 and node["returned_uj"] > 0, node  # RETURNs verified too
    books = ledger_from_status(final, [node])
    assert books.dissipated >= 0, books
    assert final["conservation"]["holds"], final["conservation"]


def test_c_auth_node_refuses_a_key_file_others_can_read(tmp_path: Path, c_node: Path) -> None:
    _, node_key = keys(tmp_path)
    key_text = node_key.read_text()
    secret = next(line for line in key_text.splitlines() if line.startswith("key="))[4:]
    node_key.chmod(0o644)
    argv = [str(c_node), "--node", "1", "-i", "socketcan", "-c", IFACE, "--nv", "n1.nv"]
    run = subprocess.run(
        [*argv, "--auth", str(node_key)], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert run.returncode == 2 and "chmod 600" in run.stderr, run.stderr
    node_key.chmod(0o600)
    for node, want in (("2", "cannot serve node 2"),):
        argv[2] = node
        run = subprocess.run(
            [*argv, "--auth", str(node_key)],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )
        assert run.returncode == 2 and want in run.stderr, run.stderr
    master = tmp_path / "master.key"
    argv[2] = "1"
    run = subprocess.run(
        [*argv, "--auth", str(master)], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert run.returncode == 2 and "not the master key" in run.stderr, run.stderr
    assert secret not in run.stderr + run.stdout
