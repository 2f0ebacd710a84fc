"""`canergy demo --topology tree`: a root, gateways on their own buses and their nodes, in virtual
time, faults on every bus and power losses of gateways, nodes and the root."""

from __future__ import annotations

import json

import pytest

from canergy.check.chain import EarlyGrantGateway
from canergy.cli import main
from canergy.demo.tree import TreeConfig, TreeRun


def test_tree_demo_ends_with_nothing_created_at_any_level(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["demo", "--topology", "tree", "--gateways", "3", "--nodes", "4", "--duration", "15s"]
    assert main([*argv, "--resets", "4", "--seed", "7", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["passive"] and out["finished"] and out["first_violation_us"] is None
    assert set(out["ledger"]["levels"]) == {"root", "gateway 1", "gateway 2", "gateway 3"}
    assert all(v["dissipated_uj"] >= 0 for v in out["ledger"]["levels"].values())
    assert set(out["ledger"]["link_gaps_uj"].values()) == {0}
    assert out["resets"]["gateways"] == 4 and out["frames_lost"] > 0 and out["decode_errors"] > 0
    assert all(level["committed"] > 0 for level in out["levels"].values())
    root = out["ledger"]["levels"]["root"]
    # drained: what the actuators did not spend is back at the root (less than 1 mJ per node
    # may stay below: a return carries whole mJ)
    assert 0 <= 30_000_000 - out["spent_uj"] - root["supervisor_usable_uj"] < 12 * 1000


def test_tree_demo_report_names_every_level(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--topology", "tree", "--duration", "5s"]) == 0
    out = capsys.readouterr().out
    assert "gateway 2" in out and "PASSIVE: nothing created at any level" in out


def test_a_gateway_granting_before_the_upstream_commit_is_caught() -> None:
    result = TreeRun(TreeConfig(duration_us=5_000_000), gateway_class=EarlyGrantGateway).run()
    assert not result.passive and result.first_violation_us is not None
    assert max(result.ledger.link_gaps.values()) > 0 or result.min_dissipated < 0


def test_tree_flags_that_do_not_apply_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--topology", "tree", "--log", "x.log"]) == 2
    assert "not with --log" in capsys.readouterr().err
