"""The C node's NV file put back from an older copy, on vcan0 against ``canergy supervisor``:
under the hardened rules the older record gets back what its actuator already used; under the
witnessed rules (``canergy-node --rules witnessed``, ``--variant witnessed``; either supervisor
core, with and without ``--auth``) the supervisor finds it behind and admits it afresh, and
nothing is created.

What the actuator used is counted over both lives (each life's ``drawn_uj``, stopped by SIGTERM so
its last status is written): the older record's own ``spent`` went back with it.

The wait for grants after the restore is timed from what the test sees: under the hardened rules
the first intention after the restore pays the older record back everything granted after the
copy, and the supervisor tops the node up again only once it has used what it then holds above
the target, at its constant power: as long as the first life ran past the copy (a loaded machine
that is slow to stop it makes that longer). Every wait shows where the books stand when it
fails."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import pytest
from support.firmware_build import c_node as c_node  # the fixtures: the C node, made up to date
from support.procs import Procs, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import POWER_UW, TARGET_UJ, c_client, keys, supervisor
from support.vcan import vcan_up as vcan_up  # and vcan0 or a failure

pytestmark = pytest.mark.vcan

NODE = 6
USED_PAST_THE_COPY_UJ = 400_000
GRANTS_S = 120
"""The time two grants may take once the node is below its target (generous: user-mode Linux on
a loaded machine)."""


@pytest.mark.parametrize(
    ("rules", "core", "auth"),
    [
        ("hardened", "c", False),
        *(("witnessed", core, auth) for auth in (False, True) for core in ("python", "c")),
    ],
    ids=lambda v: {False: "no key", True: "auth"}.get(v, v) if isinstance(v, bool) else v,
)
def test_a_c_node_restored_from_an_older_copy(
    procs: Procs, c_node: Path, rules: str, core: str, auth: bool
) -> None:
    tmp = procs.tmp
    nv, node_status = tmp / f"n{NODE}.nv", tmp / f"n{NODE}.json"
    sup_flags = ["--variant", rules, "--core", core, "--lost-after", "10", "--status-period", "0.2"]
    node_flags = ["--rules", rules, "--status-period", "0.2"]
    if auth:  # keys from `canergy keys`, as users make them
        master, node_key = keys(tmp, NODE)
        sup_flags += ["--auth", str(master)]
        node_flags += ["--auth", str(node_key)]
    supervisor(procs, str(NODE), *sup_flags)

    def books() -> dict[str, Any]:
        found: dict[str, Any] = status(tmp / "sup.json")["nodes"][str(NODE)]
        return found

    def node() -> dict[str, Any]:
        return status(node_status) if node_status.exists() else {}

    def where() -> dict[str, Any]:
        """What a failed wait shows: both sides' status and their last words."""
        sup = status(tmp / "sup.json") if (tmp / "sup.json").exists() else {}
        return {
            "supervisor": {k: sup.get(k) for k in ("usable_uj", "stopping", "uptime_s")},
            "books": sup.get("nodes", {}).get(str(NODE)),
            "node": node(),
            "stderr": {
                name: procs.stderr(name)[-1500:]
                for name in ("supervisor", f"client{NODE}")
                if (tmp / f"{name}.stderr").exists()
            },
        }

    c_client(procs, c_node, NODE, *node_flags)
    wait(
        lambda: (tmp / "sup.json").exists() and books()["committed"] >= 2, "two grants", show=where
    )
    wait(lambda: node().get("drawn_uj", 0) > 0, "the actuator running", show=where)
    copy = tmp / "older.nv"
    shutil.copyfile(nv, copy)  # the backup
    copied_at, used_at_copy = time.monotonic(), node()["drawn_uj"]
    wait(
        lambda: node()["drawn_uj"] >= used_at_copy + USED_PAST_THE_COPY_UJ,
        "the actuator using energy past the copy",
        show=where,
    )
    assert procs.stop(f"client{NODE}") == 0, procs.stderr(f"client{NODE}")
    first, ran_past_copy_s = status(node_status), time.monotonic() - copied_at
    shutil.copyfile(copy, nv)  # the backup restored
    node_status.unlink()
    done, granted = books()["committed"], books()["delivered_uj"]
    c_client(procs, c_node, NODE, *node_flags)
    # The restored record holds the books' Gs once the first intention after the restore has
    # reached it (hardened: paid back up to it; witnessed: found behind, its Rc taken from it);
    # what it then holds above the target is used up before the next top-up.
    wait(
        lambda: node().get("credited_uj", -1) >= granted,
        "the restored record holding what the books granted",
        show=where,
    )
    above_s = max(0, node()["usable_uj"] - TARGET_UJ) / POWER_UW
    wait(
        lambda: books()["committed"] >= done + 2,
        f"two grants after the restore (the first life ran {ran_past_copy_s:.1f} s past the "
        f"copy; the restored node above its target for {above_s:.1f} s)",
        timeout_s=GRANTS_S + above_s,
        show=where,
    )
    wait(
        lambda: node().get("drawn_uj", 0) >= USED_PAST_THE_COPY_UJ,
        "the actuator running again",
        show=where,
    )
    assert procs.stop(f"client{NODE}") == 0, procs.stderr(f"client{NODE}")
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")
    second, final = status(node_status), books()

    used = first["drawn_uj"] + second["drawn_uj"]
    held = second["usable_uj"] + second["return_pending_uj"] + second["released_uj"]
    let_go = final["delivered_uj"] + final["reserved_uj"] - final["returns_credited_uj"]
    created = used + held - let_go
    print(f"\n{rules}, core {core}, auth {auth}: created {created} µJ (used {used})")  # pytest -s
    if rules == "witnessed":
        assert created <= 0, (created, first, second, final)
        assert "found this record behind" in procs.stderr(f"client{NODE}")
        assert final["found_behind"] >= 1, final
    else:  # what the actuator used past the copy, used again
        assert created >= USED_PAST_THE_COPY_UJ // 2, (created, first, second, final)
