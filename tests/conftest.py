"""Hypothesis profiles: ``ci`` (default, quick) and ``long`` (HYPOTHESIS_PROFILE=long)."""

import os

import pytest
from hypothesis import HealthCheck, settings

# The helpers moved out of test modules into tests/support/ keep pytest's assertion messages.
# (Not support.recipes: its failure messages, matched by tests, stay as written.)
pytest.register_assert_rewrite(
    "support.blocked_imports",
    "support.c_binding",
    "support.cells",
    "support.client_cases",
    "support.drive_model",
    "support.hazards",
    "support.intrusion_bench",
    "support.mem_nv",
    "support.procs",
    "support.readme",
    "support.side_by_side",
    "support.vcan",
    "support.virtual_bus",
    "support.zenoh_loopback",
)

settings.register_profile(
    "ci",
    max_examples=150,
    stateful_step_count=50,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile(
    "long",
    max_examples=5000,
    stateful_step_count=200,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture(autouse=True)
def _no_terminal_size_in_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    """A screen a test prints (``canergy monitor --once``) is as wide as the terminal running
    the tests, or 160 columns without one, whatever COLUMNS and LINES say: pytest-xdist's
    workers set COLUMNS=80 (scripts/test runs two), and a shell may export its own."""
    for name in ("COLUMNS", "LINES"):
        monkeypatch.delenv(name, raising=False)


@pytest.fixture(params=["python", "c"])
def both_cores(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test on each supervisor core: for "c", ``Supervisor`` in the test's module and in
    support.live_rig builds the compiled core (``canergy.ccore``: the hardened or witnessed
    rules) instead.
    Use it with ``pytestmark = pytest.mark.usefixtures("both_cores")``."""
    if request.param == "c":
        from canergy.ccore.supervisor import CompiledSupervisor, missing

        if missing() is not None and not os.environ.get("CANERGY_REQUIRE_CCORE"):
            pytest.skip(str(missing()))

        def compiled(nodes: object, initial: int, *, variant: str = "hardened", **kw: object):  # type: ignore[no-untyped-def]
            return CompiledSupervisor(nodes, initial, variant=variant, **kw)  # type: ignore[arg-type]

        import support.live_rig

        for module in (request.module, support.live_rig):
            if hasattr(module, "Supervisor"):
                monkeypatch.setattr(module, "Supervisor", compiled)
    return str(request.param)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The vcan suite's venue and the timeouts it sized from it (support.venue), when measured."""
    from support.venue import MEASURED

    for venue in MEASURED.values():
        terminalreporter.write_line(venue.report())
