"""The C gateway (firmware/build/canergy-gateway) between two real SocketCAN buses: the Python
root supervisor on vcan0, the C gateway its node and the supervisor of vcan1, a C node and an
emulated node on vcan1. The gateway is killed with SIGKILL and restarted from its NV file (one
record for both roles); `canergy ledger` closes the tree's books from the status files."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import pytest
from support.firmware_build import c_gateway as c_gateway  # the fixtures: make the gateway
from support.firmware_build import c_node as c_node  # and the node
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT

from canergy.codec import Codec
from canergy.messages import Return

pytestmark = pytest.mark.vcan

UP, DOWN = "vcan0", "vcan1"
GW = 20


@pytest.fixture(scope="module", autouse=True)
def _both_up() -> None:
    for iface in (UP, DOWN):
        assert Path(f"/sys/class/net/{iface}/operstate").exists(), (
            f"{iface} missing: ip link add dev {iface} type vcan; ip link set up {iface}"
        )


def _gateway(procs: Procs, binary: Path) -> None:
    tmp = procs.tmp
    argv = [str(binary), "--node", str(GW), "--nodes", "1-2", "-i", "socketcan", "-c", DOWN]
    argv += ["--upstream-channel", UP, "--nv", str(tmp / "gw.nv"), "--target", "0.6J"]
    argv += ["--return-above", "5J", "--status-file", str(tmp / "gw-status.json")]
    argv += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3"]
    argv += ["--status-period", "0.2", "--response-timeout", "0.3"]
    procs.start("gateway", argv)


def test_the_c_gateway_survives_kill_9_and_the_tree_closes(
    procs: Procs, c_gateway: Path, c_node: Path
) -> None:
    tmp = procs.tmp
    gw_status = tmp / "gw-status.json"
    root = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
    root += ["--initial", "20J", "--target", "3J", "--state", str(tmp / "root.json")]
    root += ["--status-file", str(tmp / "root-status.json"), "--lost-after", "10", *TIMEOUT]
    procs.start("root", python(*root))
    _gateway(procs, c_gateway)
    below = ["-i", "socketcan", "-c", DOWN, "--power", "0.2W", "--telemetry-period", "0.5"]
    for node, program in ((1, [str(c_node)]), (2, python("-m", "firmware_model"))):
        files = ["--nv", str(tmp / f"n{node}.nv"), "--status-file", str(tmp / f"n{node}.json")]
        procs.start(f"node{node}", [*program, "--node", str(node), *files, *below, *TIMEOUT])

    def committed(node: int) -> int:
        return int(status(gw_status)["nodes"][str(node)]["committed"]) if gw_status.exists() else 0

    wait(lambda: all(committed(n) >= 2 for n in (1, 2)), "two grants per node below the gateway")
    procs.stop("gateway", signal.SIGKILL)  # mid-whatever: one record holds both roles
    credited = status(gw_status)["upstream"]["credited_uj"]
    gw_status.unlink()
    _gateway(procs, c_gateway)
    wait(lambda: gw_status.exists(), "the gateway restarting")
    wait(lambda: committed(1) + committed(2) >= 2, "grants below after the restart")
    wait(
        lambda: status(gw_status)["upstream"]["credited_uj"] > credited,
        "a grant from the root after the restart",
    )
    assert status(gw_status)["upstream"]["joins"] == 0  # its books survived: no JOIN

    # RETURNs forged in node 1's name (no key on vcan1), never credited: 1 mJ (it holds that
    # much) is held until the node's own TELEMETRY refutes it; 60 J is more than its books let
    # it hold, refuted at once
    credited = status(gw_status)["nodes"]["1"]["returns_credited_uj"]
    for amount_mj, refuted in ((1, 1), (60_000, 2)):
        seq = (int(status(tmp / "n1.json")["return_seq"]) + 1) & 0xFFFF
        arbitration_id, data = Codec().encode(Return(1, seq, amount_mj))
        forged = subprocess.run(["cansend", DOWN, f"{arbitration_id:08X}#{data.hex().upper()}"])
        assert forged.returncode == 0
        wait(
            lambda n=refuted: status(gw_status)["nodes"]["1"]["returns_refuted"] >= n,
            f"the forged RETURN of {amount_mj} mJ refuted",
        )
    assert status(gw_status)["nodes"]["1"]["returns_credited_uj"] == credited

    assert procs.stop("gateway") == 0, procs.stderr("gateway")  # settles below, then exits
    assert procs.stop("root") == 0, procs.stderr("root")
    for node in (1, 2):
        assert procs.stop(f"node{node}") == 0, procs.stderr(f"node{node}")
    gw = status(gw_status)
    assert gw["core"] == "c" and gw["link_gap_uj"] == 0 and gw["withdrawn_uj"] >= 0
    assert status(tmp / "root-status.json")["nodes"][str(GW)]["admitted"] == 1  # first start
    assert sum(status(tmp / f"n{n}.json")["spent_uj"] for n in (1, 2)) > 0
    levels = ["--level", str(tmp / "root-status.json"), str(gw_status)]
    levels += ["--level", str(gw_status), str(tmp / "n1.json"), str(tmp / "n2.json")]
    ledger = subprocess.run(
        python("-m", "canergy", "ledger", *levels),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert ledger.returncode == 0, ledger.stdout + ledger.stderr
    assert "PASSIVE" in ledger.stdout and "gateway link gap 0" in ledger.stdout
