"""A gateway between two real SocketCAN buses: the root supervisor on vcan0, the gateway a node
of vcan0 and the supervisor of vcan1, emulated nodes on vcan1; the gateway killed with SIGKILL
and restarted from its one state file. The tree's ledger closes over both buses."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import pytest
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT

from canergy.ledger import TreeLedger, ledger_from_status

pytestmark = pytest.mark.vcan

UP, DOWN = "vcan0", "vcan1"
GW = 20


@pytest.fixture(scope="module", autouse=True)
def _both_up() -> None:
    for iface in (UP, DOWN):
        assert Path(f"/sys/class/net/{iface}/operstate").exists(), (
            f"{iface} missing: ip link add dev {iface} type vcan; ip link set up {iface}"
        )


def _root(procs: Procs) -> None:
    tmp = procs.tmp
    argv = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
    argv += ["--initial", "20J", "--target", "3J", "--state", str(tmp / "root.json")]
    argv += ["--status-file", str(tmp / "root-status.json"), "--lost-after", "10", *TIMEOUT]
    procs.start("root", python(*argv))


def _gateway(procs: Procs) -> None:
    tmp = procs.tmp
    argv = ["-m", "canergy", "gateway", "--node", str(GW), "--nodes", "1-2"]
    argv += ["-i", "socketcan", "-c", DOWN, "--upstream-interface", "socketcan"]
    argv += ["--upstream-channel", UP, "--state", str(tmp / "gw.json"), "--target", "0.6J"]
    argv += ["--return-above", "5J", "--status-file", str(tmp / "gw-status.json")]
    argv += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3"]
    procs.start("gateway", python(*argv, "--lost-after", "10", *TIMEOUT))


def _node(procs: Procs, node: int) -> None:
    tmp = procs.tmp
    argv = ["-m", "firmware_model", "--node", str(node), "-i", "socketcan", "-c", DOWN]
    argv += ["--nv", str(tmp / f"n{node}.nv"), "--power", "0.2W", "--telemetry-period", "0.5"]
    procs.start(f"node{node}", python(*argv, "--status-file", str(tmp / f"n{node}.json"), *TIMEOUT))


def test_a_gateway_between_vcan0_and_vcan1_survives_kill_9(procs: Procs) -> None:
    tmp = procs.tmp
    gw_status = tmp / "gw-status.json"
    _root(procs)
    _gateway(procs)
    for node in (1, 2):
        _node(procs, node)

    def committed(node: int) -> int:
        return int(status(gw_status)["nodes"][str(node)]["committed"]) if gw_status.exists() else 0

    wait(lambda: all(committed(n) >= 2 for n in (1, 2)), "two grants per node below the gateway")
    procs.stop("gateway", signal.SIGKILL)  # mid-whatever: one file holds both roles
    credited = status(tmp / "gw.json")["upstream"]["credited_uj"]
    gw_status.unlink()
    _gateway(procs)
    wait(lambda: gw_status.exists(), "the gateway restarting")
    done = committed(1) + committed(2)
    wait(lambda: committed(1) + committed(2) > done + 2, "grants below after the restart")
    wait(
        lambda: status(gw_status)["upstream"]["credited_uj"] > credited,
        "a grant from the root after the restart",
    )
    assert status(gw_status)["upstream"]["joins"] == 0  # its books survived: no JOIN

    assert procs.stop("gateway") == 0, procs.stderr("gateway")  # settles below, then exits
    assert procs.stop("root") == 0, procs.stderr("root")
    for node in (1, 2):
        assert procs.stop(f"node{node}") == 0, procs.stderr(f"node{node}")
    root, gw = status(tmp / "root-status.json"), status(gw_status)
    nodes = [status(tmp / f"n{n}.json") for n in (1, 2)]
    tree = TreeLedger(
        {
            "root": ledger_from_status(root, [gw["upstream"]]),
            "gateway": ledger_from_status(gw, nodes),
        },
        {"gateway": gw["link_gap_uj"]},
    )
    assert tree.passive, tree.as_json()
    assert root["nodes"][str(GW)]["admitted"] == 1  # the gateway's first start only
    assert sum(n["spent_uj"] for n in nodes) > 0


def test_one_supervisor_over_vcan0_and_vcan1(procs: Procs) -> None:
    """Node 1 on each bus, one budget: grants land on the bus they name; candump of both buses
    audits clean with each bus's node 1 kept apart."""
    tmp = procs.tmp
    candump = subprocess.Popen(["candump", "-l", "any"], cwd=tmp)
    control = tmp / "sup.sock"
    argv = ["-m", "canergy", "supervisor", "--bus", f"socketcan:{UP}:1", "--bus"]
    argv += [f"socketcan:{DOWN}:1", "--initial", "10J", "--state", str(tmp / "state.json")]
    argv += ["--status-file", str(tmp / "sup.json"), "--control", str(control), *TIMEOUT]
    procs.start("supervisor", python(*argv))
    for bus in (UP, DOWN):
        node = ["-m", "firmware_model", "--node", "1", "-i", "socketcan", "-c", bus]
        node += ["--nv", str(tmp / f"{bus}.nv"), "--status-file", str(tmp / f"{bus}.json")]
        procs.start(bus, python(*node, "--telemetry-period", "0.5", *TIMEOUT))
    wait(lambda: control.exists(), "the control socket")
    wait(
        lambda: all(
            status(tmp / "sup.json")["nodes"][f"{b}/1"]["level_uj"] is not None for b in (UP, DOWN)
        ),
        "both nodes heard",
    )
    grant = ["-m", "canergy", "grant", "--control", str(control), "--amount"]
    for bus, amount in ((UP, "2J"), (DOWN, "3J")):
        done = subprocess.run(python(*grant, amount, "--node", f"{bus}/1"), timeout=120)
        assert done.returncode == 0
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    for bus in (UP, DOWN):
        assert procs.stop(bus) == 0, procs.stderr(bus)
    candump.send_signal(signal.SIGINT)
    candump.wait(30)
    final = status(tmp / "sup.json")
    assert final["nodes"][f"{UP}/1"]["delivered_uj"] == 2_000_000
    assert final["nodes"][f"{DOWN}/1"]["delivered_uj"] == 3_000_000
    assert status(tmp / f"{UP}.json")["credited_uj"] == 2_000_000
    assert status(tmp / f"{DOWN}.json")["credited_uj"] == 3_000_000
    books = ledger_from_status(final, {b: [status(tmp / f"{b}.json")] for b in (UP, DOWN)})
    assert books.passive and books.dissipated == 0
    (capture,) = tmp.glob("candump-*.log")
    audit = subprocess.run(
        python("-m", "canergy", "audit", str(capture)), capture_output=True, timeout=120
    )
    assert audit.returncode == 0, audit.stdout.decode() + audit.stderr.decode()
    assert f"{DOWN}/1" in audit.stdout.decode()
