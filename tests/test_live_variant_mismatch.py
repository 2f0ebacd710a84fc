"""A supervisor and a node running different client rules (review rv3, F3), on the live stack:
`canergy supervisor` as users run it and the emulated node on python-can's virtual bus. The node
says its rules in every TELEMETRY (``Telemetry.WITNESSED``); a supervisor whose rules differ
grants it nothing and says why: in the status (per node and in ``variant_mismatch``), once on
stderr, and in the answer to a grant asked for it.

Without the flag a witnessed supervisor granted a hardened node (whose record restored from an
older copy then creates energy, found by nobody), and a hardened supervisor granted a witnessed
node whose DEBITs it never answers (its actuator stalled, nothing said).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from test_live_gateway_old_copy import GW, Rig
from test_live_old_copy import NODE, bench, wait

from canergy.live.supervisor.control import request
from canergy.messages import Telemetry
from canergy.units import UJ_PER_J
from firmware_model.odrive.live_bench import AXIS, ENDPOINTS, LIMITS, guarded_axis, wait_for

MIXES = [("witnessed", "hardened"), ("hardened", "witnessed")]


@pytest.mark.parametrize("core", ["python", "c"])
@pytest.mark.parametrize(("supervisor", "node"), MIXES, ids=["witnessed-sup", "hardened-sup"])
def test_a_node_with_other_rules_is_granted_nothing_and_told_why(
    tmp_path: Path, core: str, supervisor: str, node: str, caplog: pytest.LogCaptureFixture
) -> None:
    b = bench(tmp_path, supervisor, None, core=core)
    b.variant = node  # the node's rules
    emulated, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("variant_mismatch", 0) >= 5)  # five TELEMETRYs taken
        asked = request(tmp_path / "ctl.sock", {"grant": {"node": NODE, "amount_uj": 100_000}}, 30)
    finally:
        loop.halt()
    status = b.stop_supervisor()
    final = status["nodes"][str(NODE)]
    why = f"node {NODE} runs the {node} rules, this supervisor the {supervisor}: nothing granted"
    assert final["rules"] == node and final["variant_mismatch"] >= 5
    assert why in status["variant_mismatch"][str(NODE)]
    assert why in asked["error"]
    assert final["committed"] == 0 and final["delivered_uj"] == 0 and final["reserved_uj"] == 0
    assert emulated.actuator.drawn_uj == 0 and emulated.client.state.usable == 0
    assert caplog.text.count(why) == 1  # once on stderr, not at every TELEMETRY


@pytest.mark.parametrize("core", ["python", "c"])
@pytest.mark.parametrize("variant", ["hardened", "witnessed"])
def test_a_node_with_the_same_rules_says_them_and_is_granted(
    tmp_path: Path, core: str, variant: str
) -> None:
    b = bench(tmp_path, variant, None, core=core)
    emulated, loop = b.start_node()
    try:
        wait(lambda: b.node_status().get("committed", 0) >= 1 and emulated.actuator.drawn_uj > 0)
    finally:
        loop.halt()
    status = b.stop_supervisor()
    final = status["nodes"][str(NODE)]
    assert final["rules"] == variant and final["variant_mismatch"] == 0
    assert status["variant_mismatch"] == {}
    said = emulated.telemetry(0).flags & Telemetry.WITNESSED
    assert bool(said) == (variant == "witnessed")


@pytest.mark.parametrize(("root", "above"), [*MIXES, ("witnessed", "witnessed")])
def test_a_gateway_says_its_rules_above(tmp_path: Path, root: str, above: str) -> None:
    """A gateway is a node upstream: its TELEMETRY says its ``--upstream-variant``."""
    rig = Rig(tmp_path, root, False)
    rig.start_root()
    rig.variant = above  # the gateway's rules above
    rig.start_gateway()
    try:
        seen = lambda: rig.status("root").get("nodes", {}).get(str(GW), {})  # noqa: E731
        wait(lambda: seen().get("rules") == above)
        grant = {"grant": {"node": GW, "amount_uj": UJ_PER_J}}
        asked = request(tmp_path / "root.sock", grant, 30)
        rig.stop("gw")
    finally:
        rig.stop("root")
    final = rig.status("root")
    if root == above:
        assert asked.get("outcome") == "COMMITTED" and final["variant_mismatch"] == {}
    else:
        why = f"node {GW} runs the {above} rules, this supervisor the {root}: nothing granted"
        assert why in asked["error"] and why in final["variant_mismatch"][str(GW)]
        assert final["nodes"][str(GW)]["delivered_uj"] == 0


def test_a_guarded_devices_proxy_is_granted_under_either_rules(tmp_path: Path) -> None:
    """A guarded ODrive axis's proxy runs inside the supervisor (its TELEMETRY has no rules
    flag): a witnessed supervisor still grants it, and the axis runs (with the flag checked
    for every node the axis timed out at 'running', granted nothing)."""
    argv = (*LIMITS, *ENDPOINTS, "--initial", "20J", "--target", "5J", "--variant", "witnessed")
    with guarded_axis(tmp_path, *argv) as b:
        wait_for(lambda: (d := b.axis_status()) is not None and d["ready"], timeout=60)
        b.run_closed_loop(1.0)
        wait_for(lambda: (d := b.axis_status()) and d["guard"] == "running", timeout=60)
        final = b.stop()
    assert final["variant_mismatch"] == {} and final["nodes"][str(AXIS)]["delivered_uj"] > 0
