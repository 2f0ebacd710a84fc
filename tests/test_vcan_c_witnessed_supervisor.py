"""The supervisor's state file put back to an older copy, on vcan0 with the C node (issue 40,
item 5): ``canergy supervisor`` grants to ``canergy-node``; the state file is copied, the
supervisor grants more, both stop; the copy is put back and the supervisor starts from it.
Under ``--variant witnessed`` (and ``canergy-node --rules witnessed``) it sends SYNC, grants
nothing while it waits for the node's books (the status says so), the node answers over real
SocketCAN when it starts, and nothing is created; under the hardened rules the restored books
count in Us again the 3 J the node received after the copy (at least 2 J seen while it runs: the
transactions the restored books number again are written off in turn, which in this one-node
run pays it back over the next seconds; another node could have been granted it meanwhile). Both
supervisor cores, with and without a key.

What the actuator used is counted over both lives of the node (each life's ``drawn_uj``, stopped
by SIGTERM so its last status is written)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from support.firmware_build import c_node as c_node  # the fixtures: the C node, made up to date
from support.procs import Procs, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import c_client, keys, supervisor
from support.vcan import vcan_up as vcan_up  # and vcan0 or a failure

from canergy.units import UJ_PER_J

pytestmark = pytest.mark.vcan

NODE = 6
GRANTED_PAST_THE_COPY_UJ = 3 * UJ_PER_J
"""Committed after the copy: what the restored books forget (the node runs at 1 W, so the
top-ups go on at 0.5 J)."""
SKEW_UJ = UJ_PER_J
"""Two grants (--max-grant 0.5 J): the two status files are written apart, so a sample may see
grants in the node's that the books' file does not show yet (one grant and 2 mJ seen)."""
CREATED_UJ = GRANTED_PAST_THE_COPY_UJ - SKEW_UJ
"""What the hardened rules are seen to create at least (the restored books forget 3 J until
reused transaction numbers, written off, make up for it)."""


def _run(procs: Procs, c_node: Path, rules: str, core: str, auth: bool) -> dict[str, Any]:
    """The restore, start to end; returns what was measured (µJ, seconds)."""
    tmp = procs.tmp
    sup_status, node_status = tmp / "sup.json", tmp / f"n{NODE}.json"
    sup_flags: list[str] = ["--variant", rules, "--core", core, "--status-period", "0.05"]
    node_flags: list[str] = ["--rules", rules, "--status-period", "0.1", "--power", "1W"]
    if auth:
        master, node_key = keys(tmp, NODE)
        sup_flags += ["--auth", str(master)]
        node_flags += ["--auth", str(node_key)]

    def books() -> dict[str, Any]:
        found: dict[str, Any] = status(sup_status).get("nodes", {}).get(str(NODE), {})
        return found

    def node() -> dict[str, Any]:
        return status(node_status) if node_status.exists() else {}

    def stop(name: str) -> None:
        assert procs.stop(name) == 0, procs.stderr(name)

    supervisor(procs, str(NODE), *sup_flags)
    c_client(procs, c_node, NODE, *node_flags)
    wait(lambda: sup_status.exists() and books().get("committed", 0) >= 2, "two grants")
    copy = (tmp / "state.json").read_bytes()  # the backup
    at_copy = books()["committed_uj"]
    wait(
        lambda: books()["committed_uj"] >= at_copy + GRANTED_PAST_THE_COPY_UJ,
        "grants past the copy",
    )
    stop(f"client{NODE}")
    first = status(node_status)
    stop("supervisor")
    first_stderr = procs.stderr("supervisor")
    (tmp / "state.json").write_bytes(copy)  # the backup restored
    sup_status.unlink()
    node_status.unlink()

    supervisor(procs, str(NODE), *sup_flags)
    wait(lambda: sup_status.exists() and books().get("state") is not None, "the restart")
    restarted = status(sup_status)
    assert restarted["core"] == core, restarted
    c_client(procs, c_node, NODE, *node_flags)
    node_started = time.monotonic()

    def created() -> int:
        """What the node used and holds beyond what the books let go, as the two status files
        show it now (they are written apart: off by up to ``SKEW_UJ``)."""
        now, ours = node(), books() if sup_status.exists() else {}
        if not now or "committed" not in ours:
            return 0
        return had(first, now) - let_go(ours)

    peaks: list[int] = []

    def watching(condition: Callable[[], bool]) -> Callable[[], bool]:
        """``condition``, sampling ``created`` on the way once the node's budget counts (under
        witnessed once the supervisor has its books: its Uc waits for the confirmation)."""

        def check() -> bool:
            books_in = sup_status.exists() and status(sup_status)["waiting_for_books"] == []
            if rules == "hardened" or books_in:
                peaks.append(created())
            return condition()

        return check

    if rules == "hardened":  # the restored books undercount until reused numbers are written off
        wait(watching(lambda: max(peaks, default=0) >= CREATED_UJ), "energy created", 60)
    wait(lambda: status(sup_status)["waiting_for_books"] == [], "the node's books", 180)
    confirmed_s = time.monotonic() - node_started
    wait(watching(lambda: books()["committed_uj"] >= UJ_PER_J), "1 J granted after the restart")
    wait(watching(lambda: node().get("drawn_uj", 0) > 0), "the actuator running again")
    restored_stderr = procs.stderr("supervisor")
    stop("supervisor")  # and a restart from its own books, the node on: it answers at once
    sup_status.unlink()
    supervisor(procs, str(NODE), *sup_flags)
    uptimes: list[float] = []  # the supervisor's uptime when its status first shows the books in

    def confirmed() -> bool:
        now = status(sup_status) if sup_status.exists() else {}
        if now.get("waiting_for_books") == [] and not uptimes:
            uptimes.append(now["uptime_s"])
        return bool(uptimes) and now["nodes"][str(NODE)]["committed"] >= 1

    wait(watching(confirmed), "a grant after a restart with the node on")
    stop(f"client{NODE}")
    stop("supervisor")
    second, final = status(node_status), books()
    return {
        "created_uj": had(first, second) - let_go(final),
        "peak_uj": max(peaks),
        "used_uj": first["drawn_uj"] + second["drawn_uj"],
        "let_go_uj": let_go(final),
        "restarted": restarted,
        "final": final,
        "confirmed_s": confirmed_s,
        "again_s": uptimes[0],
        "stderr": first_stderr + restored_stderr,
        "node_stderr": procs.stderr(f"client{NODE}"),
    }


def had(first: dict[str, Any], second: dict[str, Any]) -> int:
    """What the node had over both lives (their status files): what each life's actuator used,
    and what the second one holds (the first one's holdings are in the record it starts from)."""
    held = second["usable_uj"] + second["return_pending_uj"] + second["released_uj"]
    return int(first["drawn_uj"] + second["drawn_uj"] + held)


def let_go(books: dict[str, Any]) -> int:
    """What the supervisor's books let go to the node."""
    return int(books["delivered_uj"] + books["reserved_uj"] - books["returns_credited_uj"])


@pytest.mark.parametrize("auth", [False, True], ids=["no key", "auth"])
@pytest.mark.parametrize("core", ["c", "python"])
def test_a_restored_supervisor_state_file_waits_for_the_c_nodes_books_and_creates_nothing(
    procs: Procs, c_node: Path, core: str, auth: bool
) -> None:
    run = _run(procs, c_node, "witnessed", core, auth)
    restarted, final = run["restarted"], run["final"]
    print(  # the figures the docs quote (pytest -s)
        f"\nwitnessed, core {core}, auth {auth}: created {run['created_uj']} µJ at the end, "
        f"{run['peak_uj']} µJ at most while running (used "
        f"{run['used_uj']}, let go {run['let_go_uj']}); books confirmed "
        f"{run['confirmed_s']:.2f} s after the node started; restarted with the node on: "
        f"confirmed within {run['again_s']} s of uptime"
    )
    assert restarted["waiting_for_books"] == [NODE], restarted
    assert f"until node(s) {NODE} answer with their books" in restarted["waiting_why"]
    assert restarted["granted_this_run_uj"] == 0, restarted
    assert run["peak_uj"] <= SKEW_UJ and run["created_uj"] <= 0, run
    assert final["synced"] == 1, final
    assert f"node {NODE} confirmed its books after this start" in run["stderr"]


def test_the_same_restore_under_the_hardened_rules_creates_energy(
    procs: Procs, c_node: Path
) -> None:
    """The teeth: the restored books count again what the node received after the copy."""
    run = _run(procs, c_node, "hardened", "c", False)
    print(f"\nhardened: created {run['peak_uj']} µJ, {run['created_uj']} µJ at the end")
    assert run["restarted"]["waiting_for_books"] == [], run["restarted"]
    assert run["peak_uj"] >= CREATED_UJ, run
