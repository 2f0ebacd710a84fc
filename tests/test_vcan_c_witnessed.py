"""The C node's NV file put back from an older copy, on vcan0 against ``canergy supervisor``:
under the hardened rules the older record gets back what its actuator already used; under the
witnessed rules (``canergy-node --rules witnessed``, ``--variant witnessed``; either supervisor
core, with and without ``--auth``) the supervisor finds it behind and admits it afresh, and
nothing is created.

What the actuator used is counted over both lives (each life's ``drawn_uj``, stopped by SIGTERM so
its last status is written): the older record's own ``spent`` went back with it."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
from support.procs import Procs, status, wait
from support.procs import procs as procs  # the fixture
from support.vcan import c_client, keys, supervisor
from support.vcan import c_node as c_node  # the fixtures: the C node, built when missing
from support.vcan import vcan_up as vcan_up  # and vcan0 or a failure

pytestmark = pytest.mark.vcan

NODE = 6
USED_PAST_THE_COPY_UJ = 400_000


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
    sup_flags = ["--variant", rules, "--core", core, "--lost-after", "10"]
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

    c_client(procs, c_node, NODE, *node_flags)
    wait(lambda: (tmp / "sup.json").exists() and books()["committed"] >= 2, "two grants")
    wait(lambda: node().get("drawn_uj", 0) > 0, "the actuator running")
    copy = tmp / "older.nv"
    shutil.copyfile(nv, copy)  # the backup
    used_at_copy = node()["drawn_uj"]
    wait(
        lambda: node()["drawn_uj"] >= used_at_copy + USED_PAST_THE_COPY_UJ,
        "the actuator using energy past the copy",
    )
    assert procs.stop(f"client{NODE}") == 0, procs.stderr(f"client{NODE}")
    first = status(node_status)
    shutil.copyfile(copy, nv)  # the backup restored
    node_status.unlink()
    done = books()["committed"]
    c_client(procs, c_node, NODE, *node_flags)
    wait(lambda: books()["committed"] >= done + 2, "two grants after the restore")
    wait(lambda: node().get("drawn_uj", 0) >= USED_PAST_THE_COPY_UJ, "the actuator running again")
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
