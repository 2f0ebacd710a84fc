"""Hypothesis profiles: ``ci`` (default, quick) and ``long`` (HYPOTHESIS_PROFILE=long)."""

import os

import pytest
from hypothesis import HealthCheck, settings

# The helpers moved out of test modules into tests/support/ keep pytest's assertion messages.
# (Not support.recipes: its failure messages, matched by tests, stay as written.)
pytest.register_assert_rewrite(
    "support.blocked_imports",
    "support.c_binding",
    "support.c_cmac",
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
