"""``canergy bridge`` between two real SocketCAN buses: the Python supervisor on vcan0, a C node
(firmware/build/canergy-node) and an emulated node on vcan1, the bridge between with loss and
duplication both ways. Grants commit through it and `canergy ledger` closes the books. The same
with the pytest plugin's fixtures (the supervisor and the node as processes)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from support.firmware_build import c_node as c_node  # the fixture: makes canergy-node
from support.procs import Procs, python, status, wait
from support.procs import procs as procs  # the fixture
from support.readme import DOCS, python_blocks_of
from support.vcan import TIMEOUT

pytestmark = pytest.mark.vcan
pytest_plugins = ["pytester"]

UP, DOWN = "vcan0", "vcan1"


@pytest.fixture(scope="module", autouse=True)
def _both_up() -> None:
    for iface in (UP, DOWN):
        assert Path(f"/sys/class/net/{iface}/operstate").exists(), (
            f"{iface} missing: ip link add dev {iface} type vcan; ip link set up {iface}"
        )


def test_a_c_node_across_a_lossy_duplicating_bridge_closes_the_books(
    procs: Procs, c_node: Path
) -> None:
    tmp = procs.tmp
    bridge_status, capture = tmp / "bridge.json", tmp / "bridge.log"
    bridge = ["-m", "canergy", "bridge", "--bus1-interface", "socketcan", "--bus1-channel", UP]
    bridge += ["--bus2-interface", "socketcan", "--bus2-channel", DOWN, "--seed", "43"]
    bridge += ["--loss", "0.1", "--duplicate", "0.1", "--status-file", str(bridge_status)]
    bridge += ["--status-period", "0.2", "--log", str(capture)]
    procs.start("bridge", python(*bridge))
    wait(bridge_status.exists, "the bridge's first status")
    sup = tmp / "sup.json"
    root = ["-m", "canergy", "supervisor", "-i", "socketcan", "-c", UP, "--nodes", "1-2"]
    root += ["--initial", "20J", "--target", "1J", "--max-grant", "0.5J"]
    root += ["--state", str(tmp / "state.json"), "--status-file", str(sup), *TIMEOUT]
    procs.start("supervisor", python(*root))
    below = ["-i", "socketcan", "-c", DOWN, "--power", "0.2W", "--telemetry-period", "0.5"]
    for node, program in ((1, [str(c_node)]), (2, python("-m", "firmware_model"))):
        files = ["--nv", str(tmp / f"n{node}.nv"), "--status-file", str(tmp / f"n{node}.json")]
        procs.start(f"node{node}", [*program, "--node", str(node), *files, *below, *TIMEOUT])

    def committed(node: int) -> int:
        return int(status(sup)["nodes"][str(node)]["committed"]) if sup.exists() else 0

    def faults() -> dict[str, dict[str, int]]:
        directions: dict[str, dict[str, int]] = status(bridge_status)["directions"]
        return directions

    wait(
        lambda: (
            all(committed(n) >= 3 for n in (1, 2))
            and all(c["lost"] and c["duplicated"] for c in faults().values())
        ),
        "three grants per node through the bridge, each direction losing and duplicating",
        show=lambda: (status(sup) if sup.exists() else None, faults()),
    )
    assert procs.stop("supervisor") == 0, procs.stderr("supervisor")  # settles, then exits
    for node in (1, 2):
        assert procs.stop(f"node{node}") == 0, procs.stderr(f"node{node}")
    assert procs.stop("bridge") == 0, procs.stderr("bridge")
    assert sum(status(tmp / f"n{n}.json")["spent_uj"] for n in (1, 2)) > 0
    ledger = subprocess.run(
        python("-m", "canergy", "ledger", "--json", "--level", str(sup), *_nodes(tmp)),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert ledger.returncode == 0, ledger.stdout + ledger.stderr
    assert json.loads(ledger.stdout)["passive"] is True
    counts = status(bridge_status)["directions"]
    channels = {line.split()[1] for line in capture.read_text().splitlines()}
    assert channels == {UP, DOWN}
    assert sum(c["forwarded"] for c in counts.values()) > 0
    assert "canergy bridge: vcan0 <-> vcan1, seed 43" in procs.stderr("bridge")


def _nodes(tmp: Path) -> list[str]:
    return [str(tmp / f"n{n}.json") for n in (1, 2)]


def test_the_plugin_runs_a_c_node_process_behind_a_bridge_on_vcan(
    pytester: pytest.Pytester, c_node: Path
) -> None:
    """docs/testing.md's vcan example, the plugin's process paths: the supervisor as a process on
    vcan0, the C node spawned on vcan1 with its status file in the books, the bridge between;
    the books close."""
    example = python_blocks_of(DOCS / "testing.md")[1]  # as printed, the node's path made whole
    example = example.replace('"firmware/build/canergy-node"', repr(str(c_node)))
    pytester.makepyfile(test_user=example)
    result = pytester.runpytest("-p", "no:cacheprovider", f"--basetemp={pytester.path / 't'}")
    result.assert_outcomes(passed=1)
    assert list(pytester.path.rglob("node1-status.json"))


POWER_CUT = """
import pytest

NODE = {node!r}


@pytest.mark.canergy(interface="socketcan", channel="vcan0", faults="loss=0.1,duplicate=0.1")
def test_a_c_node_cut_off_its_power_twice(
    canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn
):
    below = canergy_bus.sibling("vcan1")
    canergy_bridge(canergy_bus, below)
    slow = ["--response-timeout", "0.3"]
    node = canergy_spawn(
        [NODE, "--node", "1", "-i", "{{interface}}", "-c", "{{channel}}", "--nv", "{{tmp}}/n1.nv",
         "--status-file", "{{status}}", "--power", "0.5W", *slow],
        "node1",
        bus=below,
    )
    sup = canergy_supervisor(
        "--nodes", "1", "--initial", "20J", "--target", "1J", "--max-grant", "0.3J", *slow
    )
    for cut in range(2):
        done = sup.status()["nodes"]["1"]["committed"]
        sup.wait_for(lambda s: s["nodes"]["1"]["committed"] >= done + 2, "two more grants")
        node.power_cut()
        node.restart()
    done = sup.status()["nodes"]["1"]["committed"]
    sup.wait_for(lambda s: s["nodes"]["1"]["committed"] > done, "a grant after the last cut")
"""


def test_the_plugin_cuts_a_c_nodes_power_and_the_books_close(
    pytester: pytest.Pytester, c_node: Path
) -> None:
    """A spawned C node cut off (SIGKILL) twice and restarted from its NV file, behind the
    marker's faults: grants resume and the books close at teardown."""
    pytester.makepyfile(test_user=POWER_CUT.format(node=str(c_node)))
    result = pytester.runpytest("-p", "no:cacheprovider", f"--basetemp={pytester.path / 't'}")
    result.assert_outcomes(passed=1)
    assert (pytester.path / "t").exists()


AUTHENTICATED = """
import pytest

NODE = {node!r}


@pytest.mark.canergy(interface="socketcan", channel="vcan0", faults="loss=0.1,duplicate=0.1")
def test_an_authenticated_c_node_behind_a_faulty_bridge(
    canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn
):
    below = canergy_bus.sibling("vcan1")
    canergy_bridge(canergy_bus, below)
    slow = ["--response-timeout", "0.3"]
    sup = canergy_supervisor(
        "--nodes", "1", "--initial", "20J", "--target", "1J", "--max-grant", "0.5J", *slow,
        auth=True,
    )
    canergy_spawn(
        [NODE, "--node", "1", "-i", "{{interface}}", "-c", "{{channel}}", "--nv", "{{tmp}}/n1.nv",
         "--status-file", "{{status}}", "--power", "0.2W", "--auth", str(sup.node_key(1)), *slow],
        "node1",
        bus=below,
    )
    status = sup.wait_for(lambda s: s["nodes"]["1"]["committed"] >= 3, "three grants")
    # the bridge's losses part frames from their MAC frames (classic layout); none fails its MAC
    split = {{"frame without a MAC", "MAC frame without its message"}}
    assert set(status.get("auth_failures", {{}})) <= split, status["auth_failures"]
"""


def test_the_plugin_runs_an_authenticated_c_node(pytester: pytest.Pytester, c_node: Path) -> None:
    """``canergy_supervisor(auth=True)`` makes a master key and derives the node's: the C node
    in authenticated mode is granted across the marker's faults and the books close."""
    pytester.makepyfile(test_user=AUTHENTICATED.format(node=str(c_node)))
    result = pytester.runpytest("-p", "no:cacheprovider", f"--basetemp={pytester.path / 't'}")
    result.assert_outcomes(passed=1)
