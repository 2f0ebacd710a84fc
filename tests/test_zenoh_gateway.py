"""A root supervisor and a gateway in separate processes, joined by Eclipse Zenoh on loopback
(``tcp/127.0.0.1`` only, no scouting), frames lost and duplicated on that leg; the gateway's own
bus carries an emulated node (Zenoh too: python-can's virtual bus does not cross processes).
The gateway is killed with SIGKILL and restarted; the tree's ledger closes."""

from __future__ import annotations

import signal

from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.zenoh_loopback import endpoint, free_port, site

from canergy.cli import main
from canergy.ledger import TreeLedger, ledger_from_status

GW = 7
FAST = ["--response-timeout", "0.1"]


def test_root_and_gateway_processes_over_zenoh_survive_kill_9(procs: Procs) -> None:
    tmp = procs.tmp
    up_site, down_site = site(), site()
    up_port, down_port = free_port(), free_port()
    root = ["-m", "canergy", "supervisor", "-i", "zenoh", "-c", up_site, "--nodes", str(GW)]
    root += ["--bus-kwargs", f"listen={endpoint(up_port)}", "--initial", "20J", "--target", "3J"]
    root += ["--state", str(tmp / "root.json"), "--status-file", str(tmp / "root-status.json")]
    procs.start("root", python(*root, "--status-period", "0.2", *FAST))
    node = ["-m", "firmware_model", "--node", "1", "-i", "zenoh", "-c", down_site, "--bus-kwargs"]
    node += [f"listen={endpoint(down_port)}", "--nv", str(tmp / "n1.nv"), "--power", "0.5W"]
    node += ["--status-file", str(tmp / "n1.json"), "--telemetry-period", "0.2", *FAST]
    procs.start("node", python(*node))
    gateway = ["-m", "canergy", "gateway", "--node", str(GW), "--nodes", "1"]
    gateway += ["-i", "zenoh", "-c", down_site, "--bus-kwargs", f"connect={endpoint(down_port)}"]
    gateway += ["--upstream-interface", "zenoh", "--upstream-channel", up_site]
    gateway += ["--upstream-bus-kwargs", f"connect={endpoint(up_port)}"]
    gateway += ["--upstream-loss", "0.1", "--upstream-duplicate", "0.1", "--fault-seed", "3"]
    gateway += ["--state", str(tmp / "gw.json"), "--status-file", str(tmp / "gw-status.json")]
    gateway += ["--target", "1J", "--return-above", "6J", "--upstream-response-timeout", "0.1"]
    gateway += ["--telemetry-period", "0.1", "--status-period", "0.2", *FAST]
    gw_status = tmp / "gw-status.json"

    def credited() -> int:
        return int(status(gw_status)["upstream"]["credited_uj"]) if gw_status.exists() else 0

    procs.start("gateway", python(*gateway))
    wait(lambda: credited() >= 3_000_000, "the root granting to the gateway over Zenoh", 90)
    wait(lambda: status(gw_status)["nodes"]["1"]["committed"] >= 2, "grants below", 90)
    procs.stop("gateway", signal.SIGKILL)
    before = status(tmp / "gw.json")["upstream"]["credited_uj"]
    admitted = status(tmp / "root-status.json")["nodes"][str(GW)]["admitted"]  # JOINs answered
    gw_status.unlink()
    procs.start("gateway", python(*gateway))
    wait(lambda: credited() > before, "a grant from the root after the restart", 90)
    assert status(gw_status)["upstream"]["joins"] == 0  # its books survived

    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")
    assert procs.stop("node") == 0, procs.stderr("node")
    root_books, gw = status(tmp / "root-status.json"), status(gw_status)
    levels = {"root": ledger_from_status(root_books, [gw["upstream"]])}
    levels["gateway"] = ledger_from_status(gw, [status(tmp / "n1.json")])
    tree = TreeLedger(levels, {"gateway": gw["link_gap_uj"]})
    assert tree.passive, tree.as_json()
    files = [str(tmp / name) for name in ("root-status.json", "gw-status.json", "n1.json")]
    argv = ["ledger", "--level", files[0], files[1], "--level", files[1], files[2]]
    assert main(argv) == 0  # the same books, closed by the command
    assert root_books["nodes"][str(GW)]["admitted"] == admitted  # no JOIN after the restart
