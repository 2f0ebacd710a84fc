"""A user's test with the pytest plugin against nodes that decide by the C client library
(firmware/'s rules, in this process through cffi, on python-can's virtual bus): it passes, and
the same test fails naming the node and the energy it created against the library's ``broken``
build (a duplicated COMMIT credited again), behind a bridge that duplicates every frame."""

from __future__ import annotations

import pytest
import support.c_host  # noqa: F401  imported here, so pytester's runs in this process keep it

pytest_plugins = ["pytester"]

USER_TEST = """
from canergy.codec import Codec
from canergy.live.runtime import BusRuntime, monotonic_us
from canergy.messages import Direction
from canergy.testing.run import Loop
from firmware_model.__main__ import status
from firmware_model.actuator import PowerProfile
from firmware_model.node import FirmwareNode, NodeConfig
from firmware_model.nvstore import NvStore
from support.c_host import {host} as Host


def test_grants_through_a_duplicating_bridge(
    canergy_bus, canergy_books, canergy_supervisor, canergy_bridge, tmp_path
):
    below = canergy_bus.sibling()
    config = NodeConfig(power=PowerProfile.constant(0.5))
    nv = NvStore(tmp_path / "1.nv", 1, fsync=False)
    host = Host([FirmwareNode(1, nv, config, monotonic_us())])
    runtime = BusRuntime(below.open(), host, codec=Codec(), receives=Direction.TO_CLIENT)
    loop = Loop(runtime)
    canergy_books.add_client(lambda: status(host, runtime), stop=loop.halt)
    canergy_bridge(canergy_bus, below, duplicate=1.0, seed=5)
    sup = canergy_supervisor("--nodes", "1", "--initial", "10J", "--target", "1J",
                             "--max-grant", "0.4J", "--response-timeout", "100ms")
    sup.wait_for(lambda s: s["nodes"]["1"]["committed"] >= 3, "three grants")
"""


def _run(pytester: pytest.Pytester, host: str) -> pytest.RunResult:
    pytester.makepyfile(test_user=USER_TEST.format(host=host))
    return pytester.runpytest("-p", "no:cacheprovider", "-q", f"--basetemp={pytester.path / 't'}")


def test_the_c_library_passes(pytester: pytest.Pytester) -> None:
    _run(pytester, "CHost").assert_outcomes(passed=1)


def test_its_broken_build_fails_naming_the_node(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "BrokenCHost")
    result.assert_outcomes(passed=1, errors=1)  # the test passed; its teardown closed the books
    result.stdout.fnmatch_lines(
        ["*canergy: the books do not close: * J created; node 1 created * J: it holds *"]
    )
