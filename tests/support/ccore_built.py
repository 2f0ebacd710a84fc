"""The mark of tests that need the compiled core's release build (``canergy.ccore``): skipped
where it is not built, unless the run requires it (``scripts/test`` builds it and sets
``CANERGY_REQUIRE_CCORE``, so there a missing build fails instead)."""

from __future__ import annotations

import os

import pytest

from canergy.ccore.supervisor import missing

release = pytest.mark.skipif(
    missing() is not None and not os.environ.get("CANERGY_REQUIRE_CCORE"),
    reason=f"{missing()} (scripts/test builds it and sets CANERGY_REQUIRE_CCORE)",
)
