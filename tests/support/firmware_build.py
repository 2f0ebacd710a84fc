"""The C programs under firmware/build for the tests that run them as processes: ``built`` runs
``make`` for the target every time (quick when it is up to date), so a binary older than its
sources is rebuilt before a test runs it; ``c_node`` and ``c_gateway`` are module fixtures over
it (import them into a test module by name)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"


def built(target: str) -> Path:
    """``firmware/TARGET`` (``build/canergy-node``), made up to date; a build that fails fails
    the test loudly."""
    build = subprocess.run(
        ["make", "-s", "-C", str(FIRMWARE), target], capture_output=True, text=True, timeout=600
    )
    assert build.returncode == 0, f"make {target} failed:\n{build.stdout}{build.stderr}"
    binary = FIRMWARE / target
    assert os.access(binary, os.X_OK), f"{binary} was not built"
    return binary


@pytest.fixture(scope="module")
def c_node() -> Path:
    return built("build/canergy-node")


@pytest.fixture(scope="module")
def c_gateway() -> Path:
    return built("build/canergy-gateway")
