"""Hypothesis profiles: ``ci`` (default, quick) and ``long`` (HYPOTHESIS_PROFILE=long)."""

import os

import pytest
from hypothesis import HealthCheck, settings

pytest.register_assert_rewrite("cells")

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
