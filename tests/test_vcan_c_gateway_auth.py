"""The C gateway authenticated above (``canergy-gateway --upstream-auth``) on real SocketCAN
buses: the Python root supervisor with the master key on vcan0 (classic frames and MAC frames,
or CAN FD), the C gateway its node 20 with the node key `canergy keys` derives, a C node below
on vcan1 without a key. Every frame of the gateway is verified by the root; forgeries in the
gateway's name with the public codec are refused and counted by the gateway, nothing forged is
credited, and `canergy ledger` closes the tree's books."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from support.firmware_build import c_gateway as c_gateway  # the fixtures: make the gateway
from support.firmware_build import c_node as c_node  # and the node
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT, keys

from canergy.codec import Codec
from canergy.live.supervisor.control import request
from canergy.messages import Commit, Intention, Return
from canergy.units import UJ_PER_J

pytestmark = pytest.mark.vcan

UP, DOWN = "vcan0", "vcan1"
GW = 20
CODEC = Codec()


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


# --- authenticated below too (canergy-gateway --auth): a Python emulated node with its key ------


def _tree_keys(tmp: Path) -> tuple[Path, Path, Path, Path]:
    """The root's master key and node 20's key from it; the gateway's own master key and node
    1's key from that (`canergy keys`)."""
    root_master, gw_key = keys(tmp, GW)
    below = tmp / "below"
    below.mkdir()
    gw_master, node_key = keys(below, 1)
    return root_master, gw_key, gw_master, node_key


def _forged_returns(fd: bool) -> list[str]:
    """A RETURN of 65.535 J in node 1's name below (cansend's syntax), plain and with a made-up
    MAC in the layout's shape: what a device without the key can send."""
    arbitration_id, data = CODEC.encode(Return(1, 1, 65535))
    frames = [f"{arbitration_id:08X}#{data.hex().upper()}"]
    if fd:
        body = data + bytes(20 - len(data) - 12) + (1).to_bytes(4, "big") + bytes(8)
        frames.append(f"{arbitration_id:08X}##1{body.hex().upper()}")
    else:
        mac_frame = bytes([Return.TYPE, 0, 0, 1, 2, 3, 4, 5])
        frames.append(f"{CODEC.id_base | 0x800 | 1:08X}#{mac_frame.hex().upper()}")
    return frames


@pytest.mark.parametrize("fd", [True, False], ids=["fd", "classic"])
def test_the_c_gateway_authenticated_on_both_legs_grants_a_keyed_node_and_refuses_forgeries(
    procs: Procs, c_gateway: Path, fd: bool
) -> None:
    """Root (``--auth``) -> C gateway (``--upstream-auth``, ``--auth``) -> ``python -m
    firmware_model --auth``: energy reaches the node with a MAC on every frame of both legs
    (nothing refused anywhere), keyless RETURNs in the node's name are refused by the gateway and
    move nothing, and `canergy ledger` finds the tree passive."""
    layout = ["--fd"] if fd else []
    for iface in (UP, DOWN) if fd else ():
        mtu = int(Path(f"/sys/class/net/{iface}/mtu").read_text())
        assert mtu >= 72, f"CAN FD needs {iface} at mtu 72: ip link set {iface} mtu 72"
    tmp = procs.tmp
    root_master, gw_key, gw_master, node_key = _tree_keys(tmp)
    root_status, gw_status, n1 = tmp / "root-status.json", tmp / "gw-status.json", tmp / "n1.json"
    root = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
    root += ["--initial", "20J", "--target", "3J", "--state", str(tmp / "root.json")]
    root += ["--status-file", str(root_status), "--status-period", "0.2", "--lost-after", "10"]
    root += ["--auth", str(root_master), *layout, *TIMEOUT]
    procs.start("root", python(*root))
    gw = [str(c_gateway), "--node", str(GW), "--nodes", "1", "-i", "socketcan", "-c", DOWN]
    gw += ["--upstream-channel", UP, "--nv", str(tmp / "gw.nv"), "--target", "0.6J"]
    gw += ["--return-above", "5J", "--status-file", str(gw_status), "--status-period", "0.2"]
    gw += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3"]
    gw += ["--response-timeout", "0.3", "--upstream-auth", str(gw_key), "--auth", str(gw_master)]
    procs.start("gateway", gw + (["--upstream-fd", "--fd"] if fd else []))
    node = ["-m", "firmware_model", "--node", "1", "-i", "socketcan", "-c", DOWN, *layout]
    node += ["--auth", str(node_key), "--nv", str(tmp / "n1.nv"), "--power", "0.2W"]
    node += ["--status-file", str(n1), "--status-period", "0.2", "--telemetry-period", "0.5"]
    procs.start("node1", python(*node, *TIMEOUT))

    def below() -> dict[str, Any]:
        found: dict[str, Any] = status(gw_status)["nodes"]["1"] if gw_status.exists() else {}
        return found

    wait(lambda: below().get("committed", 0) >= 2, "grants below", show=below)
    gateway = status(gw_status)
    assert gateway["auth"] == ("fd" if fd else "classic") and gateway["refused"]["total"] == 0
    assert gateway["upstream"]["auth_refused"] == 0, gateway["upstream"]
    credited = below()["returns_credited_uj"]
    for frame in _forged_returns(fd):
        subprocess.run(["cansend", DOWN, frame], check=True, timeout=30)
    wait(lambda: status(gw_status)["refused"]["total"] >= 1, "the forgeries refused", show=below)
    done = below()["committed"]
    wait(lambda: below()["committed"] >= done + 1, "grants after the forgeries", show=below)
    assert below()["returns_credited_uj"] < credited + 65_535_000  # nothing forged credited

    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")
    assert procs.stop("node1") == 0, procs.stderr("node1")
    gateway = status(gw_status)
    assert gateway["refused"]["by_node"]["1"]["total"] == gateway["nodes"]["1"]["refused"] >= 1
    assert status(root_status)["refused"]["total"] == 0
    levels = ["--level", str(root_status), str(gw_status), "--level", str(gw_status), str(n1)]
    ledger = subprocess.run(
        python("-m", "canergy", "ledger", *levels), capture_output=True, text=True, timeout=120
    )
    assert ledger.returncode == 0, ledger.stdout + ledger.stderr
    assert "PASSIVE" in ledger.stdout and "gateway link gap 0" in ledger.stdout


def test_the_c_gateway_restored_from_an_older_copy_with_keys_on_both_legs_creates_nothing(
    procs: Procs, c_gateway: Path
) -> None:
    """tests/test_vcan_c_gateway_old_copy.py's witnessed case with a key on each leg and a keyed
    node below: the root grants the gateway 3 J, 0.5 J of which goes to node 1; the NV file is
    copied; the gateway returns 2 J above; the copy is put back while the root is off. The
    restored gateway waits, the root finds it behind, it drops the Us below: nothing created,
    and the node below keeps working under the gateway's keys."""
    tmp = procs.tmp
    root_master, gw_key, gw_master, node_key = _tree_keys(tmp)
    nv, gw_status, root_status = tmp / "gw.nv", tmp / "gw-status.json", tmp / "root-status.json"
    n1 = tmp / "n1.json"

    def root() -> None:
        argv = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
        argv += ["--variant", "witnessed", "--initial", "30J", "--state", str(tmp / "root.json")]
        argv += ["--status-file", str(root_status), "--status-period", "0.2"]
        argv += ["--control", str(tmp / "root.sock"), "--lost-after", "10", *TIMEOUT]
        argv += ["--auth", str(root_master)]
        root_status.unlink(missing_ok=True)
        procs.start("root", python(*argv))
        wait((tmp / "root.sock").exists, "the root's control socket")
        wait(root_status.exists, "the root's status: its loop runs (SIGTERM is handled)")

    def gateway(*extra: str) -> None:
        gw_status.unlink(missing_ok=True)
        argv = [str(c_gateway), "--node", str(GW), "--nodes", "1", "-c", DOWN, "--nv", str(nv)]
        argv += ["--upstream-channel", UP, "--upstream-rules", "witnessed", "--target", "0.5J"]
        argv += ["--status-file", str(gw_status), "--status-period", "0.2"]
        argv += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3"]
        argv += ["--upstream-auth", str(gw_key), "--auth", str(gw_master), *extra]
        procs.start("gateway", argv)
        wait(gw_status.exists, "the gateway's status")

    def gw() -> dict[str, Any]:
        return status(gw_status)

    def session() -> dict[str, Any]:
        found: dict[str, Any] = status(root_status)["nodes"][str(GW)]
        return found

    def released() -> int:
        s = session()
        return int(s["delivered_uj"] + s["reserved_uj"] - s["returns_credited_uj"])

    def held() -> int:
        g = gw()
        below = g["usable_uj"] + g["reserved_uj"] + g["delivered_uj"] - g["returns_credited_uj"]
        return int(below + g["upstream"]["usable_uj"] + g["upstream"]["return_pending_uj"])

    node = ["-m", "firmware_model", "--node", "1", "-i", "socketcan", "-c", DOWN]
    node += ["--auth", str(node_key), "--nv", str(tmp / "n1.nv"), "--telemetry-period", "0.3"]
    node += ["--status-file", str(n1), "--status-period", "0.2"]
    procs.start("node1", python(*node, *TIMEOUT))
    root()
    gateway()
    grant = {"grant": {"node": GW, "amount_uj": 3 * UJ_PER_J}}
    assert request(tmp / "root.sock", grant, 60).get("outcome") == "COMMITTED"
    wait(lambda: gw()["nodes"]["1"]["delivered_uj"] == UJ_PER_J // 2, "0.5 J below", show=gw)
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    shutil.copy(nv, tmp / "gw.nv.copy")
    gateway("--return-above", "0.5J")
    wait(lambda: session()["returns_credited_uj"] == 2 * UJ_PER_J, "2 J returned", show=session)
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")

    shutil.copy(tmp / "gw.nv.copy", nv)  # the older copy put back
    gateway()
    wait(lambda: gw()["waiting_for_upstream"] is not None, "the wait in the status", show=gw)
    root()
    wait(lambda: gw()["upstream"]["found_behind"] == 1, "found behind", show=gw)
    wait(lambda: session()["synced"] == 1, "the root's SYNC answered", show=session)
    assert held() <= released() == UJ_PER_J  # nothing created
    assert gw()["upstream"]["dropped_below_uj"] == int(2.5 * UJ_PER_J)
    assert gw()["refused"]["total"] == 0 and gw()["upstream"]["auth_refused"] == 0
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")
    assert procs.stop("node1") == 0, procs.stderr("node1")
    assert status(root_status)["refused"]["total"] == 0
