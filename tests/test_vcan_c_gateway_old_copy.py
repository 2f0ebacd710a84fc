"""The C gateway's NV file put back from an older copy, on vcan0 (above) and vcan1 (below),
against ``canergy supervisor`` as the root. The root grants the gateway 3 J, which it forwards
below; the NV file is copied; in its next life the gateway returns 2 J upstream; the copy is put
back and the gateway started from it while the root is off, then the root again. Under the
hardened rules above the gateway holds the 3 J below again (2 J created); with
``--upstream-rules witnessed`` it waits (status and stderr), the root finds it behind, and it drops
the Us below: nothing created. No node runs below in the first test: what is measured is between
the root and the gateway. The second puts a C node below, drawing, so that one restore rolls
back both links."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import pytest
from support.firmware_build import c_gateway as c_gateway  # the fixtures: make the gateway
from support.firmware_build import c_node as c_node  # and the node
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import TIMEOUT

from canergy.live.supervisor.control import request
from canergy.units import UJ_PER_J

pytestmark = pytest.mark.vcan

UP, DOWN = "vcan0", "vcan1"
GW = 20


@pytest.fixture(scope="module", autouse=True)
def _both_up() -> None:
    for iface in (UP, DOWN):
        assert Path(f"/sys/class/net/{iface}/operstate").exists(), f"{iface} missing"


@pytest.mark.parametrize("rules", ["hardened", "witnessed"])
def test_a_c_gateway_restored_from_an_older_copy(procs: Procs, c_gateway: Path, rules: str) -> None:
    tmp = procs.tmp
    nv, gw_status, root_status = tmp / "gw.nv", tmp / "gw-status.json", tmp / "root-status.json"

    def root() -> None:
        argv = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
        argv += ["--variant", rules, "--initial", "30J", "--state", str(tmp / "root.json")]
        argv += ["--status-file", str(root_status), "--status-period", "0.2"]
        argv += ["--control", str(tmp / "root.sock"), "--lost-after", "10", *TIMEOUT]
        root_status.unlink(missing_ok=True)  # the last root's would answer for the new one
        procs.start("root", python(*argv))
        wait((tmp / "root.sock").exists, "the root's control socket")
        wait(root_status.exists, "the root's status: its loop runs (SIGTERM is handled)")

    def gateway(*extra: str) -> None:
        gw_status.unlink(missing_ok=True)
        argv = [str(c_gateway), "--node", str(GW), "--nodes", "1", "-c", DOWN]
        argv += ["--upstream-channel", UP, "--nv", str(nv), "--upstream-rules", rules]
        argv += ["--status-file", str(gw_status), "--status-period", "0.2"]
        argv += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3", *extra]
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

    root()
    gateway()
    grant = {"grant": {"node": GW, "amount_uj": 3 * UJ_PER_J}}
    assert request(tmp / "root.sock", grant, 60).get("outcome") == "COMMITTED"
    wait(lambda: gw()["usable_uj"] == 3 * UJ_PER_J, "3 J forwarded below", show=gw)
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    shutil.copy(nv, tmp / "gw.nv.copy")
    gateway("--return-above", "1J")
    wait(lambda: session()["returns_credited_uj"] == 2 * UJ_PER_J, "2 J returned", show=session)
    wait(lambda: gw()["usable_uj"] == UJ_PER_J, "1 J left below", show=gw)
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")

    shutil.copy(tmp / "gw.nv.copy", nv)  # the older copy put back
    gateway()
    if rules == "witnessed":
        wait(lambda: gw()["waiting_for_upstream"] is not None, "the wait in the status", show=gw)
        assert gw()["upstream"]["resuming"] is True
    else:
        wait(lambda: gw()["usable_uj"] == 3 * UJ_PER_J, "the copy's 3 J below", show=gw)
        assert gw()["waiting_for_upstream"] is None
    root()
    if rules == "witnessed":
        wait(lambda: gw()["upstream"]["found_behind"] == 1, "found behind", show=gw)
        wait(lambda: session()["synced"] == 1, "the root's SYNC answered", show=session)
        assert held() <= released() == UJ_PER_J  # nothing created
        assert gw()["upstream"]["dropped_below_uj"] == 3 * UJ_PER_J
        assert gw()["waiting_for_upstream"] is None and gw()["link_gap_uj"] == 0
        said = procs.stderr("gateway")
        assert "no grant below until the supervisor above confirms" in said
        assert "found this gateway's record behind (an older copy)" in said
    else:
        wait(lambda: session()["lost"] is False, "the root hearing the gateway", show=session)
        assert held() - released() == 2 * UJ_PER_J  # created
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("root") == 0, procs.stderr("root")


@pytest.mark.parametrize("rules", ["hardened", "witnessed"])
def test_one_restore_rolls_back_both_links_with_a_c_node_drawing_below(
    procs: Procs, c_gateway: Path, c_node: Path, rules: str
) -> None:
    """The gateway's NV file holds its record above and its sessions below: one restore puts
    both links back. The root grants 3 J; the gateway tops the C node on vcan1 up to 0.6 J
    while it draws 0.3 W; the NV file is copied; in its next life the gateway returns all
    but 1 J above and goes on topping the node up; the copy is put back and started (the
    root and the node on). Hardened rules on both links: the copy holds again what went back
    above and what the node was given since (both created). Witnessed rules on both links:
    found behind above (its Us below dropped) and the node's books raise its session below to
    what the node received (a debt): what the node used and holds and what the gateway
    holds stay within what the root released."""
    tmp = procs.tmp
    nv, gw_status, root_status = tmp / "gw.nv", tmp / "gw-status.json", tmp / "root-status.json"
    root = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", str(GW)]
    root += ["--variant", rules, "--initial", "30J", "--state", str(tmp / "root.json")]
    root += ["--status-file", str(root_status), "--status-period", "0.2"]
    root += ["--control", str(tmp / "root.sock"), "--lost-after", "10", *TIMEOUT]
    procs.start("root", python(*root))
    wait((tmp / "root.sock").exists, "the root's control socket")
    wait(root_status.exists, "the root's status")
    node = [str(c_node), "--node", "1", "-i", "socketcan", "-c", DOWN, "--nv", str(tmp / "n1.nv")]
    node += ["--status-file", str(tmp / "n1.json"), "--status-period", "0.2", "--power", "0.3W"]
    procs.start("node", [*node, "--telemetry-period", "0.3", "--rules", rules, *TIMEOUT])

    def gateway(*extra: str) -> None:
        gw_status.unlink(missing_ok=True)
        argv = [str(c_gateway), "--node", str(GW), "--nodes", "1", "-c", DOWN, "--nv", str(nv)]
        argv += ["--upstream-channel", UP, "--rules", rules, "--upstream-rules", rules]
        argv += ["--status-file", str(gw_status), "--status-period", "0.2", "--target", "0.6J"]
        argv += ["--upstream-response-timeout", "0.3", "--telemetry-period", "0.3", *extra]
        procs.start("gateway", [*argv, *TIMEOUT])
        wait(gw_status.exists, "the gateway's status")

    def gw() -> dict[str, Any]:
        return status(gw_status)

    def below() -> dict[str, Any]:
        found: dict[str, Any] = gw()["nodes"]["1"]
        return found

    gateway()
    grant = {"grant": {"node": GW, "amount_uj": 3 * UJ_PER_J}}
    assert request(tmp / "root.sock", grant, 60).get("outcome") == "COMMITTED"
    wait(lambda: below()["committed"] >= 2, "two top-ups of the node", show=below)
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    shutil.copy(nv, tmp / "gw.nv.copy")
    given = status(tmp / "gw-status.json")["delivered_uj"]  # to the node, as the copy holds it

    gateway("--return-above", "1J")
    wait(lambda: below()["committed"] >= 2, "two top-ups after the copy", show=below)
    wait(lambda: status(root_status)["nodes"][str(GW)]["returns_credited_uj"] > 0, "a return")
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert gw()["delivered_uj"] > given  # the node was given more since the copy

    shutil.copy(tmp / "gw.nv.copy", nv)  # the older copy put back: both links at once
    gateway()
    if rules == "witnessed":
        wait(lambda: gw()["upstream"]["found_behind"] == 1, "found behind above", show=gw)
        wait(lambda: gw()["unconfirmed"] == [], "the node's books below", show=gw)
        assert gw()["delivered_uj"] > given  # its session raised to what the node received
    else:
        wait(lambda: gw()["upstream"]["usable_uj"] + gw()["usable_uj"] > 0, "the copy's budget")
    time.sleep(2)  # the node draws on; the gateway tops it up if it can
    assert procs.stop("gateway") == 0, procs.stderr("gateway")
    assert procs.stop("node") == 0, procs.stderr("node")
    assert procs.stop("root") == 0, procs.stderr("root")

    root_session = status(root_status)["nodes"][str(GW)]
    released = root_session["delivered_uj"] + root_session["reserved_uj"]
    released -= root_session["returns_credited_uj"]
    g, n = gw(), status(tmp / "n1.json")
    at_gateway = max(g["usable_uj"], 0) + g["upstream"]["usable_uj"]
    at_gateway += g["upstream"]["return_pending_uj"]
    at_node = n["spent_uj"] + n["usable_uj"] + n["return_pending_uj"]
    if rules == "witnessed":
        assert at_gateway + at_node <= released, (at_gateway, at_node, released)
        assert g["upstream"]["dropped_below_uj"] > 0 and g["link_gap_uj"] == 0
    else:
        assert at_gateway + at_node > released, (at_gateway, at_node, released)  # created
