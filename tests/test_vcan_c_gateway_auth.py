"""The C gateway authenticated above (``canergy-gateway --upstream-auth``) on real SocketCAN
buses: the Python root supervisor with the master key on vcan0 (classic frames and MAC frames,
or CAN FD), the C gateway its node 20 with the node key `canergy keys` derives, a C node below
on vcan1 without a key. Every frame of the gateway is verified by the root; forgeries in the
gateway's name with the public codec are refused and counted by the gateway, nothing forged is
credited, and `canergy ledger` closes the tree's books."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT, built, keys
from support.vcan import c_node as c_node  # the fixture: builds canergy-node when missing

from canergy.codec import Codec
from canergy.messages import Commit, Intention

pytestmark = pytest.mark.vcan

UP, DOWN = "vcan0", "vcan1"
GW = 20
CODEC = Codec()


@pytest.fixture(scope="module")
def c_gateway() -> Path:
    return built("build/canergy-gateway")


def _forgeries(fd: bool, tx: int) -> list[str]:
    """What a device without the key can send to node 20 (cansend's syntax): a COMMIT and an
    INTENTION of 65.535 J, plain and with a made-up MAC in the layout's shape."""
    frames = []
    for msg in (Commit(GW, tx + 1, 65535), Intention(GW, tx + 1, 65535, 0)):
        arbitration_id, data = CODEC.encode(msg)
        frames.append(f"{arbitration_id:08X}#{data.hex().upper()}")
        if fd:
            body = data + bytes(20 - len(data) - 12) + (tx + 1).to_bytes(4, "big") + bytes(8)
            frames.append(f"{arbitration_id:08X}##1{body.hex().upper()}")
        else:
            mac_frame = bytes([msg.TYPE]) + bytes(2) + bytes.fromhex("0102030405")
            frames.append(f"{CODEC.id_base | GW:08X}#{mac_frame.hex().upper()}")
    return frames


@pytest.mark.parametrize("fd", [True, False], ids=["fd", "classic"])
def test_the_c_gateway_authenticated_above_is_granted_and_refuses_forgeries(
    procs: Procs, c_gateway: Path, c_node: Path, fd: bool
) -> None:
    if fd:
        mtu = int(Path(f"/sys/class/net/{UP}/mtu").read_text())
        assert mtu >= 72, f"CAN FD needs {UP} at mtu 72: ip link set {UP} mtu 72"
    tmp = procs.tmp
    master, node_key = keys(tmp, GW)
    root_status, gw_status = tmp / "root-status.json", tmp / "gw-status.json"
    root = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
    root += ["--initial", "20J", "--target", "3J", "--state", str(tmp / "root.json")]
    root += ["--status-file", str(root_status), "--status-period", "0.2", "--lost-after", "10"]
    root += ["--auth", str(master), *(["--fd"] if fd else []), *TIMEOUT]
    procs.start("root", python(*root))
    gw = [str(c_gateway), "--node", str(GW), "--nodes", "1", "-i", "socketcan", "-c", DOWN]
    gw += ["--upstream-channel", UP, "--nv", str(tmp / "gw.nv"), "--target", "0.6J"]
    gw += ["--return-above", "5J", "--status-file", str(gw_status), "--status-period", "0.2"]
    gw += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3"]
    gw += ["--response-timeout", "0.3", "--upstream-auth", str(node_key)]
    procs.start("gateway", gw + (["--upstream-fd"] if fd else []))
    below = ["--node", "1", "-i", "socketcan", "-c", DOWN, "--power", "0.2W"]
    below += ["--nv", str(tmp / "n1.nv"), "--status-file", str(tmp / "n1.json")]
    procs.start("node1", [str(c_node), *below, "--telemetry-period", "0.5", *TIMEOUT])

    def committed() -> int:
        return int(status(gw_status)["nodes"]["1"]["committed"]) if gw_status.exists() else 0

    def root_committed() -> int:
        if not root_status.exists():
            return 0
        return int(status(root_status)["nodes"][str(GW)]["committed"])

    wait(lambda: committed() >= 2 and root_committed() >= 1, "grants above and below")
    up = status(gw_status)["upstream"]
    assert up["authenticated"] is True and up["joins"] == 1 and up["auth_refused"] == 0, up
    assert status(root_status)["refused"]["total"] == 0  # every frame of the gateway verified

    for frame in _forgeries(fd, int(up["last_tx"]) & 0xFFFF):
        subprocess.run(["cansend", UP, frame], check=True, timeout=30)
    wait(lambda: status(gw_status)["upstream"]["auth_refused"] >= 2, "the forgeries refused")
    done = root_committed()
    wait(lambda: root_committed() >= done + 1 or committed() >= 4, "grants after the forgeries")

    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")
    assert procs.stop("node1") == 0, procs.stderr("node1")
    final, gateway = status(root_status), status(gw_status)
    # nothing forged credited (one forged COMMIT alone was 65.535 J)
    assert gateway["upstream"]["credited_uj"] <= final["nodes"][str(GW)]["delivered_uj"]
    assert gateway["link_gap_uj"] == 0
    # the root refused only the forgeries (frames in its own direction), no frame of the gateway
    reasons = final["refused"]["by_node"][str(GW)]["reasons"]
    assert all("in the supervisor's direction" in r for r in reasons), reasons
    levels = ["--level", str(root_status), str(gw_status)]
    levels += ["--level", str(gw_status), str(tmp / "n1.json")]
    ledger = subprocess.run(
        python("-m", "canergy", "ledger", *levels), capture_output=True, text=True, timeout=120
    )
    assert ledger.returncode == 0, ledger.stdout + ledger.stderr
    assert "PASSIVE" in ledger.stdout and "gateway link gap 0" in ledger.stdout
