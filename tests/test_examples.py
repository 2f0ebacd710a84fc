"""examples/my_node, a user's project, as canergy's suite runs it (pytester, on python-can's
virtual bus): its fault test passes against nodes that keep the rules, and the same test fails
against a node that credits its grants twice, naming the node and the energy it created.
``scripts/test-examples`` runs the whole project from canergy's wheel in a fresh venv, on the
virtual bus and on vcan0."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "my_node"
FAULT_TEST = "tests/test_faults.py::test_grants_commit_through_a_faulty_link[duplicate]"


def _example(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    """The example's fault test under duplication, run as its project runs it."""
    shutil.copytree(EXAMPLE / "tests", pytester.path / "tests")
    shutil.copy2(EXAMPLE / "pyproject.toml", pytester.path)
    pytester.syspathinsert(EXAMPLE)  # my_node, as pip installs it for the project
    basetemp = f"--basetemp={pytester.path / 'tmp'}"
    return pytester.runpytest("-p", "no:cacheprovider", "-q", basetemp, FAULT_TEST, *args)


def test_the_examples_test_passes_against_nodes_that_keep_the_rules(
    pytester: pytest.Pytester,
) -> None:
    _example(pytester).assert_outcomes(passed=1)


def test_the_examples_test_fails_against_a_node_that_credits_twice(
    pytester: pytest.Pytester,
) -> None:
    result = _example(pytester, "--node-host", "support.greedy:Greedy")
    result.assert_outcomes(passed=1, errors=1)  # the books, closed at teardown
    result.stdout.fnmatch_lines(
        ["*canergy: the books do not close: * J created; node 2 created * J: it holds *"]
    )
