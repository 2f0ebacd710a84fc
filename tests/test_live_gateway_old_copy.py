"""A gateway's state file put back to an older copy, on the live stack: `canergy supervisor` above
and `canergy gateway` as users run them, on python-can's virtual buses (issue 40, item 6, for the
Python gateway). The gateway is granted 3 J and forwards it below; its file is copied; in its next
life it returns 2 J upstream; the copy is put back. Under the hardened rules upstream the restored
gateway holds the 3 J below again while the root holds the 2 J it was given back: 2 J created.
Under ``--upstream-variant witnessed`` the gateway starts RESUMING, says so (status and stderr)
and grants nothing below until the root answers; the root finds the record behind (it holds a
debit the copy lacks), and the gateway drops its upstream books and the budget below: nothing is
created, with and without a key.

No node runs below: what is measured is between the root and the gateway.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import can
import pytest
from support.live_rig import Loop

from canergy.cli import main
from canergy.codec import Codec
from canergy.core import Timing
from canergy.ledger import TreeLedger, ledger_from_status
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.live.supervisor.control import request
from canergy.messages import Direction
from canergy.units import UJ_PER_J
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore

GW = 20


class Rig:
    """The root and the gateway, each a CLI run in a thread, restartable."""

    def __init__(self, tmp: Path, variant: str, auth: bool, below: str = "hardened") -> None:
        self.tmp, self.variant, self.auth, self.below = tmp, variant, auth, below
        self.up, self.down = f"gwold-up-{uuid.uuid4().hex}", f"gwold-down-{uuid.uuid4().hex}"
        self.threads: dict[str, threading.Thread] = {}
        self.results: dict[str, list[int]] = {}
        if auth:
            assert main(["keys", "-o", str(tmp / "root.key")]) == 0
            node_key = ["--nodes", str(GW), "-o", str(tmp / "gw.key")]
            assert main(["keys", "--master", str(tmp / "root.key"), *node_key]) == 0

    def _start(self, name: str, argv: list[str]) -> None:
        sock = self.tmp / f"{name}.sock"
        result: list[int] = []
        self.results[name] = result
        self.threads[name] = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
        self.threads[name].start()
        wait(sock.exists, 30)

    def start_root(self) -> None:
        t = self.tmp
        argv = ["supervisor", "-i", "virtual", "-c", self.up, "--variant", self.variant]
        argv += ["--nodes", str(GW), "--initial", "30J", "--state", str(t / "root.json")]
        argv += ["--status-file", str(t / "root-status.json"), "--control", str(t / "root.sock")]
        argv += ["--no-fsync", "--status-period", "50ms", "--response-timeout", "100ms"]
        self._start("root", argv + (["--auth", str(t / "root.key")] if self.auth else []))

    def start_gateway(self, *extra: str) -> None:
        t = self.tmp
        (t / "gw-status.json").unlink(missing_ok=True)
        argv = ["gateway", "--node", str(GW), "--nodes", "1", "-i", "virtual", "-c", self.down]
        argv += ["--upstream-interface", "virtual", "--upstream-channel", self.up]
        argv += ["--upstream-variant", self.variant, "--variant", self.below]
        argv += ["--state", str(t / "gw.json")]
        argv += ["--status-file", str(t / "gw-status.json"), "--control", str(t / "gw.sock")]
        argv += ["--no-fsync", "--status-period", "50ms", "--telemetry-period", "50ms"]
        argv += ["--upstream-response-timeout", "100ms", "--stop-timeout", "1s", *extra]
        self._start("gw", argv + (["--upstream-auth", str(t / "gw.key")] if self.auth else []))

    def stop(self, name: str) -> None:
        assert request(self.tmp / f"{name}.sock", {"stop": True}, 30)
        self.threads[name].join(timeout=60)
        assert self.results[name] == [0]

    def status(self, name: str) -> dict[str, Any]:
        try:
            data: dict[str, Any] = json.loads((self.tmp / f"{name}-status.json").read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}
        return data

    def released(self) -> int:
        """What the root's books let go to the gateway: delivered and reserved, less what it
        credited back."""
        s = self.status("root")["nodes"][str(GW)]
        return int(s["delivered_uj"] + s["reserved_uj"] - s["returns_credited_uj"])

    def held(self) -> int:
        """What the gateway holds: its budget below (usable, reserved, out at its nodes), and
        above what it was credited and not yet forwarded or returned."""
        g = self.status("gw")
        below = g["usable_uj"] + g["reserved_uj"] + g["delivered_uj"] - g["returns_credited_uj"]
        return int(below + g["upstream"]["usable_uj"] + g["upstream"]["return_pending_uj"])

    def tree(self) -> TreeLedger:
        """The tree's ledger from the two status files (``canergy ledger``'s reading)."""
        root, gw = self.status("root"), self.status("gw")
        levels = {"root": ledger_from_status(root, [gw["upstream"]])}
        idle = {"node": 1, "return_seq": 0}  # the node below: never on, never granted anything
        idle |= dict.fromkeys(("usable_uj", "credited_uj", "spent_uj", "return_pending_uj"), 0)
        levels["gateway"] = ledger_from_status(gw, [idle])
        return TreeLedger(levels, {"gateway": gw["link_gap_uj"]})


def wait(condition: Any, timeout_s: float = 60.0) -> None:
    """Until ``condition()``: the CLIs run on the wall clock, so the bound is generous."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"condition not met within {timeout_s} s"
        time.sleep(0.02)


def restored(tmp: Path, variant: str, auth: bool, below: str = "hardened") -> Rig:
    """3 J granted and forwarded; the gateway's file copied; 2 J returned upstream in its next
    life; both stopped, the copy put back, the gateway started from it (the root still off)."""
    rig = Rig(tmp, variant, auth, below)
    rig.start_root()
    rig.start_gateway()
    try:
        grant = {"grant": {"node": GW, "amount_uj": 3 * UJ_PER_J}}
        assert request(tmp / "root.sock", grant, 30).get("outcome") == "COMMITTED"
        wait(lambda: rig.status("gw").get("usable_uj") == 3 * UJ_PER_J)  # forwarded below
        rig.stop("gw")
        copy = (tmp / "gw.json").read_text()
        rig.start_gateway("--return-above", "1J")
        wait(lambda: rig.status("root")["nodes"][str(GW)]["returns_credited_uj"] == 2 * UJ_PER_J)
        wait(lambda: rig.status("gw").get("usable_uj") == UJ_PER_J)
        rig.stop("gw")
    finally:
        rig.stop("root")
    (tmp / "gw.json").write_text(copy)
    rig.start_gateway()
    return rig


@pytest.mark.parametrize(
    ("auth", "below"), [(False, "hardened"), (True, "hardened")], ids=["no key", "auth"]
)
def test_an_older_copy_of_a_gateways_record_creates_nothing_under_witnessed(
    tmp_path: Path, auth: bool, below: str, caplog: pytest.LogCaptureFixture
) -> None:
    rig = restored(tmp_path, "witnessed", auth, below)
    try:
        wait(lambda: rig.status("gw").get("waiting_for_upstream") is not None)
        waiting = rig.status("gw")
        assert (
            "no grant below until the supervisor above confirms" in waiting["waiting_for_upstream"]
        )
        assert waiting["upstream"]["resuming"] is True and waiting["granted_this_run_uj"] == 0
        rig.start_root()  # SYNC from above; the gateway answers with its books and counts
        wait(lambda: rig.status("gw").get("upstream", {}).get("found_behind") == 1)
        wait(lambda: rig.status("root")["nodes"][str(GW)]["synced"] == 1)
        assert rig.held() <= rig.released() == UJ_PER_J  # 1 J released, none created
        assert rig.tree().passive, rig.tree().as_json()
        after = rig.status("gw")
        assert after["waiting_for_upstream"] is None and after["upstream"]["resuming"] is False
        assert after["upstream"]["dropped_below_uj"] == 3 * UJ_PER_J
        assert after["link_gap_uj"] == 0
    finally:
        rig.stop("gw")
        rig.stop("root")
    said = caplog.text
    assert "RESUME sent upstream; no grant below until the supervisor above confirms" in said
    assert "found this gateway's record behind (an older copy)" in said


def test_witnessed_below_a_restarted_gateway_returns_nothing_before_its_nodes_books(
    tmp_path: Path,
) -> None:
    """Witnessed rules below too: a start waits for the nodes' books, and Us below (maybe an
    older copy's, holding what a node was granted since) goes back up only once they are in
    (``Gateway.can_give_back``; found by ``canergy check --topology chain --variant witnessed
    --gateway-old-copies 1``). Node 1 below is never on: nothing is returned."""
    rig = Rig(tmp_path, "witnessed", False, "witnessed")
    rig.start_root()
    rig.start_gateway()
    try:
        grant = {"grant": {"node": GW, "amount_uj": 3 * UJ_PER_J}}
        assert request(tmp_path / "root.sock", grant, 30).get("outcome") == "COMMITTED"
        wait(lambda: rig.status("gw").get("usable_uj") == 3 * UJ_PER_J)
        rig.stop("gw")
        rig.start_gateway("--return-above", "1J")
        wait(lambda: rig.status("gw").get("waiting_for_books") == [1])
        wait(lambda: rig.status("gw").get("upstream", {}).get("resuming") is False)
        time.sleep(1.0)  # twenty status periods: a return would have gone
        assert rig.status("root")["nodes"][str(GW)]["returns_credited_uj"] == 0
        assert rig.status("gw")["usable_uj"] == 3 * UJ_PER_J
    finally:
        rig.stop("gw")
        rig.stop("root")


def test_the_same_restore_with_hardened_rules_upstream_creates_energy(tmp_path: Path) -> None:
    """The measurement the witnessed rules answer: the restored gateway holds below again the
    2 J it returned upstream after the copy."""
    rig = restored(tmp_path, "hardened", False)
    try:
        wait(lambda: rig.status("gw").get("usable_uj") == 3 * UJ_PER_J)
        assert rig.status("gw")["waiting_for_upstream"] is None  # no wait: nothing asked above
        rig.start_root()
        wait(lambda: rig.status("root").get("nodes", {}).get(str(GW), {}).get("lost") is False)
        assert rig.held() - rig.released() == 2 * UJ_PER_J
        assert not rig.tree().passive  # `canergy ledger` reports it
    finally:
        rig.stop("gw")
        rig.stop("root")


def node_below(rig: Rig) -> tuple[FirmwareNode, Loop]:
    """Node 1 on the bus below (the emulator, witnessed rules, drawing 0.5 W) from its NV file."""
    timing = Timing(response_timeout_us=100_000, retries=3, command_timeout_us=200_000)
    config = NodeConfig(
        power=PowerProfile.constant(0.5),
        telemetry_period_us=100_000,
        timing=timing,
        variant="witnessed",
    )
    nv = NvStore(rig.tmp / "node.nv", 1, fsync=False)
    node = FirmwareNode(1, nv, config, monotonic_us())
    codec = Codec()
    bus = can.Bus(interface="virtual", channel=rig.down, can_filters=codec.client_watch_filters(1))
    host = NodeHost([node])
    return node, Loop(BusRuntime(bus, host, codec=codec, receives=Direction.TO_CLIENT))


def test_start_without_a_node_that_never_comes_back_lets_the_gateway_return_and_creates_nothing(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Witnessed rules on both legs. Node 1 below is granted and draws; it goes off for good
    and the gateway restarts. Without ``--start-without 1`` the gateway waits for its books for
    ever (the test above: nothing returned); with it, the start writes off what node 1's books
    say it holds (status ``started_without``, stderr) and what the gateway holds above
    ``--return-above`` goes back up. The tree's books: nothing created (the root let go at least
    what the gateway holds, node 1 has and its actuator used; `canergy ledger`'s arithmetic)."""
    rig = Rig(tmp_path, "witnessed", False, "witnessed")
    below = ("--target", "1J", "--max-grant", "0.5J", "--response-timeout", "100ms")
    rig.start_root()
    rig.start_gateway(*below)
    node, loop = node_below(rig)
    try:
        grant = {"grant": {"node": GW, "amount_uj": 3 * UJ_PER_J}}
        assert request(tmp_path / "root.sock", grant, 30).get("outcome") == "COMMITTED"
        wait(lambda: node.actuator.drawn_uj >= UJ_PER_J // 4)
        wait(lambda: rig.status("gw")["nodes"]["1"]["committed"] >= 2)
    finally:
        loop.halt()  # node 1 is off, for good
    try:
        rig.stop("gw")
        rig.start_gateway("--response-timeout", "100ms", "--return-above", "1J")
        rig.stop("gw")  # a start without the flag: waits for node 1, returns nothing
        assert rig.status("root")["nodes"][str(GW)]["returns_credited_uj"] == 0
        rig.start_gateway("--response-timeout", "100ms", "--return-above", "1J", *WITHOUT)
        wait(lambda: rig.status("gw").get("usable_uj") == UJ_PER_J)
        wait(lambda: rig.status("root")["nodes"][str(GW)]["returns_credited_uj"] > 0)
        gw = rig.status("gw")
        s = gw["nodes"]["1"]
        held_below = s["delivered_uj"] + s["reserved_uj"] - s["returns_credited_uj"]
        assert held_below > 0 and gw["started_without"] == {"1": held_below}
        assert gw["waiting_for_books"] == [] and s["state"] == "SYNCING"  # its own session waits
        c = node.client.state
        assert node.actuator.drawn_uj + c.usable + c.return_pending + node.ready_uj <= held_below
        wait(lambda: rig.held() == rig.released())
        assert rig.held() <= rig.released() <= 3 * UJ_PER_J
        levels = {"root": ledger_from_status(rig.status("root"), [rig.status("gw")["upstream"]])}
        levels["gateway"] = ledger_from_status(rig.status("gw"), [node.status()])
        tree = TreeLedger(levels, {"gateway": rig.status("gw")["link_gap_uj"]})
        assert tree.passive, tree.as_json()
    finally:
        rig.stop("gw")
        rig.stop("root")
    said = "started without node(s) 1 (--start-without): not waited for; written off what"
    assert said in caplog.text


WITHOUT = ("--start-without", "1")
