"""The SocketCAN recipes of the README and the site (docs/) run as written on vcan0 and vcan1
(``pytest -m vcan``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from support.recipes import run_session, sessions
from support.vcan import vcan_up

pytestmark = pytest.mark.vcan
__all__ = ["vcan_up"]  # the fixture of support.vcan that fails the tests here without vcan0


@pytest.mark.parametrize("name", sorted(sessions("vcan")))
def test_readme_recipe_on_vcan(name: str, tmp_path: Path) -> None:
    run_session(sessions("vcan")[name], tmp_path)
