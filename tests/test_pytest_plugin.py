"""canergy's pytest plugin as a user's suite meets it (pytester): a test of nodes across a faulty
bridge passes with the documented fixtures, fails naming the node that created energy when the
node breaks the rules, and passes again once it is fixed; ``-p no:canergy`` turns it off."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.readme import DOCS, python_blocks_of

# imported here, so pytester's runs in this process keep it: zenoh's native module does not
# import a second time once pytester dropped it after a run
import canergy.live.transports.zenoh_bus  # noqa: F401
from canergy.testing.books import creation, terms

pytest_plugins = ["pytester"]

USER_TESTS = '''
import pytest

from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from canergy.testing.run import Loop
from firmware_model.__main__ import status
from firmware_model.node import FirmwareNode, NodeConfig, NodeHost
from firmware_model.nvstore import NvStore
from support.greedy import Greedy  # node 2 credits every grant twice

GREEDY = {greedy}


@pytest.fixture
def nodes(canergy_bus, canergy_books, tmp_path):
    """The device under test: two emulated nodes on a bus of their own, in this process."""
    below = canergy_bus.sibling()
    now = monotonic_us()
    host = (Greedy if GREEDY else NodeHost)(
        [
            FirmwareNode(n, NvStore(tmp_path / f"{{n}}.nv", n, fsync=False), NodeConfig(), now)
            for n in (1, 2)
        ]
    )
    runtime = BusRuntime(below.open(), host, codec=Codec(), receives=Direction.TO_CLIENT)
    loop = Loop(runtime)
    canergy_books.add_client(lambda: status(host, runtime), stop=loop.halt)
    yield below
    loop.halt()


def test_grants_across_a_lossy_duplicating_bridge(
    canergy_bus, canergy_supervisor, canergy_bridge, nodes
):
    bridge = canergy_bridge(canergy_bus, nodes, loss=0.1, duplicate=0.1, seed=43)
    sup = canergy_supervisor(
        "--nodes", "1-2", "--initial", "10J", "--target", "1J", "--max-grant", "0.5J",
        "--response-timeout", "50ms",
    )
    sup.wait_for(
        lambda s: all(n["committed"] >= 1 for n in s["nodes"].values()),
        "a grant committed to each node",
    )
    assert sup.grant(2, "0.3J")["outcome"] in ("COMMITTED", "ABORTED")
    assert sum(c["frames"] for c in bridge.status()["directions"].values()) > 0
'''


def test_the_documented_example_passes_as_printed(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(test_docs=python_blocks_of(DOCS / "testing.md")[0])
    result = pytester.runpytest("-p", "no:cacheprovider", f"--basetemp={pytester.path / 't'}")
    result.assert_outcomes(passed=1)


def _suite(pytester: pytest.Pytester, greedy: bool) -> pytest.RunResult:
    pytester.makepyfile(test_user=USER_TESTS.format(greedy=greedy))
    return pytester.runpytest("-p", "no:cacheprovider", "-q", f"--basetemp={pytester.path / 'tmp'}")


def test_a_users_test_passes_against_nodes_that_keep_the_rules(
    pytester: pytest.Pytester,
) -> None:
    result = _suite(pytester, greedy=False)
    result.assert_outcomes(passed=1)
    captures = list(pytester.path.rglob("canergy-capture.log"))
    assert captures and captures[0].read_text().count("\n") > 10  # kept for canergy audit


def test_the_same_test_fails_naming_the_node_that_created_energy(
    pytester: pytest.Pytester,
) -> None:
    result = _suite(pytester, greedy=True)
    result.assert_outcomes(passed=1, errors=1)  # the test passed; its teardown closed the books
    result.stdout.fnmatch_lines(["*canergy: the books do not close: * created; node 2 created *"])


def test_books_false_opts_out_and_no_canergy_turns_the_plugin_off(
    pytester: pytest.Pytester,
) -> None:
    opted_out = USER_TESTS.format(greedy=True).replace(
        "def test_grants", "@pytest.mark.canergy(books=False)\ndef test_grants"
    )
    pytester.makepyfile(test_user=opted_out)
    pytester.runpytest("-p", "no:cacheprovider", "-q").assert_outcomes(passed=1)
    off = pytester.runpytest("-p", "no:cacheprovider", "-q", "-p", "no:canergy")
    off.assert_outcomes(errors=1)
    off.stdout.fnmatch_lines(["*fixture 'canergy_bus' not found*"])


def test_the_terms_name_the_party_and_add_up_to_the_ledger() -> None:
    supervisor = {
        "initial_uj": 10_000_000,
        "usable_uj": 9_000_000,
        "injected_uj": 0,
        "nodes": {
            "1": {"reserved_uj": 0, "delivered_uj": 500_000, "returns_credited": 0,
                  "returns_credited_uj": 0},
            "2": {"reserved_uj": 0, "delivered_uj": 500_000, "returns_credited": 0,
                  "returns_credited_uj": 0},
        },
    }  # fmt: skip
    node = {"credited_uj": 500_000, "spent_uj": 100_000, "return_seq": 0, "return_pending_uj": 0}
    honest = [{**node, "node": 1, "usable_uj": 400_000}, {**node, "node": 2, "usable_uj": 400_000}]
    assert creation(supervisor, honest) is None
    greedy = [honest[0], {**honest[1], "usable_uj": 700_000}]
    why = creation(supervisor, greedy)
    assert why is not None and "0.300000 J created; node 2 created 0.300000 J" in why
    assert "usable 0.700000 J + spent 0.100000 J" in why
    parts = terms(supervisor, greedy)
    assert sum(t.dissipated for t in parts) == -300_000
    assert [t.who for t in parts] == ["the supervisor", "node 1", "node 2"]


MARKED = """
import time

import can
import pytest


@pytest.mark.canergy(faults="loss=1,partition=1s+2s", seed=5)
def test_the_markers_faults(canergy_bus, canergy_bridge):
    below = canergy_bus.sibling()
    bridge = canergy_bridge(canergy_bus, below)
    status = bridge.status()
    assert status["seed"] == 5 and status["profile"]["loss"] == 1.0
    assert status["partitions"] == ["1s+2s"]
    with canergy_bus.open() as bus, below.open() as far:
        bus.send(can.Message(arbitration_id=0x123, data=b"x"))
        deadline = time.monotonic() + 30
        while list(bridge.status()["directions"].values())[0]["lost"] < 1:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert far.recv(0) is None  # decided lost, as the marker says: never sent


@pytest.mark.canergy(nodes="3-4", books=False)
def test_the_markers_nodes(canergy_supervisor):
    assert sorted(canergy_supervisor("--initial", "1J").status()["nodes"]) == ["3", "4"]


@pytest.mark.canergy(faults="loss=2")
def test_a_bad_marker_is_named(canergy_bus, canergy_bridge):
    with pytest.raises(ValueError, match="loss probability 2.0 outside 0..1"):
        canergy_bridge(canergy_bus, canergy_bus.sibling())
"""


def test_the_marker_gives_the_bridge_its_faults_and_the_supervisor_its_nodes(
    pytester: pytest.Pytester,
) -> None:
    pytester.makepyfile(test_marked=MARKED)
    pytester.runpytest("-p", "no:cacheprovider", "-q").assert_outcomes(passed=3)


UNREGISTERED = """
def test_nodes_never_registered(canergy_supervisor):
    canergy_supervisor("--nodes", "1-2", "--initial", "1J")


def test_two_supervisors(canergy_supervisor, canergy_bus):
    canergy_supervisor("--nodes", "1", "--initial", "1J")
    canergy_supervisor("--nodes", "1", "--initial", "1J", bus=canergy_bus.sibling(), name="b")
"""


def test_books_that_cannot_be_closed_say_why(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(test_unregistered=UNREGISTERED)
    result = pytester.runpytest("-p", "no:cacheprovider", "-q")
    result.assert_outcomes(passed=2, errors=2)
    result.stdout.fnmatch_lines(
        ["*cannot close the books (*): the supervisor's nodes are 1, 2, the clients' statuses "
         "given are of none; register each node's status*",
         "*2 supervisors in one test: the plugin closes the books of one; close them in the "
         "test*"]
    )  # fmt: skip


def test_a_part_that_fails_to_stop_does_not_leave_the_others_running(tmp_path: Path) -> None:
    from canergy.testing.plugin import Books

    stopped: list[str] = []

    def stuck() -> None:
        stopped.append("stuck")
        raise AssertionError("node 1 did not stop")

    books = Books(tmp_path)
    books.add_client(lambda: {}, stop=stuck)
    books.add_client(lambda: {}, stop=lambda: stopped.append("node 2"))
    books.bridges.append(lambda: stopped.append("bridge"))
    with pytest.raises(AssertionError, match="node 1 did not stop"):
        books.stop_all()
    assert stopped == ["stuck", "node 2", "bridge"]


def test_a_zenoh_bus_names_its_endpoint_to_processes_and_has_fresh_siblings() -> None:
    from canergy.testing.bus import TestBus

    bus = TestBus.zenoh(fd=True)
    assert bus.flags == [
        *("-i", "zenoh", "-c", bus.channel, "--fd", "--bus-kwargs", f"connect={bus.endpoint}")
    ]
    other = bus.sibling()
    assert (other.interface, other.fd) == ("zenoh", True)
    assert other.channel != bus.channel and other.endpoint != bus.endpoint


POWER_CUTS = """
import time

import pytest

from canergy.testing.bus import TestBus

FAST = ["--response-timeout", "0.2"]
NODE = ["{python}", "-m", "firmware_model", "--node", "1", "{bus}", "--nv", "{tmp}/n1.nv",
        "--no-fsync", "--status-file", "{status}", "--status-period", "0.2", "--power", "0.5W",
        "--telemetry-period", "0.2", *FAST]
SEEN = {}


def start(canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn, **faults):
    below = TestBus.zenoh()  # the emulator is a process: it cannot hear the virtual bus
    bridge = canergy_bridge(canergy_bus, below, **faults)
    node = canergy_spawn(NODE, "node1", bus=below)
    sup = canergy_supervisor("--nodes", "1", "--initial", "20J", "--target", "1J",
                             "--max-grant", "0.3J", *FAST)
    return bridge, node, sup


def wait_power(bridge, what, condition):
    deadline = time.monotonic() + 60
    while not condition(bridge.status()["power"].get("node1", {})):
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


@pytest.mark.canergy(faults="loss=0.05,duplicate=0.05,cut=node1@3s+1s", seed=3)
def test_the_markers_power_cut(canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn):
    bridge, node, sup = start(canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn)
    sup.wait_for(lambda s: s["nodes"]["1"]["committed"] >= 1, "a grant")
    wait_power(bridge, "the cut and the restart", lambda c: c.get("restarts") == 1)
    assert bridge.status()["power"] == {"node1": {"cuts": 1, "restarts": 1, "off": False}}
    assert bridge.status()["power_cuts"] == ["node1@3s+1s"]
    assert node.starts == 2
    done = sup.status()["nodes"]["1"]["committed"]
    sup.wait_for(lambda s: s["nodes"]["1"]["committed"] > done, "a grant after the restart")


def test_a_cut_still_on_at_the_end(canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn):
    bridge, node, sup = start(canergy_bus, canergy_supervisor, canergy_bridge, canergy_spawn,
                              power_cuts=["node1@2s+10min"])
    wait_power(bridge, "the cut", lambda c: c.get("cuts") == 1)
    assert node.popen.poll() is not None  # killed
    SEEN["node"] = node


def test_the_teardown_ended_the_cut():
    node = SEEN["node"]  # started again before the supervisor stopped, then stopped (SIGTERM)
    assert (node.starts, node.popen.returncode) == (2, 0)
"""


def test_the_documented_power_cut_passes_as_printed(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(test_docs=python_blocks_of(DOCS / "testing.md")[2])
    result = pytester.runpytest("-p", "no:cacheprovider", f"--basetemp={pytester.path / 't'}")
    result.assert_outcomes(passed=1)


def test_the_bridge_cuts_a_node_processs_power_and_the_books_close(
    pytester: pytest.Pytester,
) -> None:
    """The emulator as a process (on Zenoh over loopback, behind the bridge from the virtual
    bus): the marker's ``cut=node1@3s+1s`` kills it and starts it again, counted, grants resume
    and the books close across the cut; a cut still on when the test ends is ended at teardown
    (the node started again, then stopped with the supervisor settled) and the books close."""
    pytester.makepyfile(test_power=POWER_CUTS)
    result = pytester.runpytest("-p", "no:cacheprovider", "-q", f"--basetemp={pytester.path / 't'}")
    result.assert_outcomes(passed=3)
    [status] = pytester.path.rglob("test_the_markers_power_cut0/node1-status.json")
    assert json.loads(status.read_text())["credited_uj"] > 0
