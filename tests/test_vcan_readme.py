"""The README's SocketCAN recipes run as written on vcan0 and vcan1 (``pytest -m vcan``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_readme_recipes import run_session, sessions
from test_vcan import _vcan_up

pytestmark = pytest.mark.vcan
__all__ = ["_vcan_up"]  # the fixture of test_vcan that brings vcan0 and vcan1 up


@pytest.mark.parametrize("name", sorted(sessions("vcan")))
def test_readme_recipe_on_vcan(name: str, tmp_path: Path) -> None:
    run_session(sessions("vcan")[name], tmp_path)
