"""docs/transitions.md and the state diagrams are generated from the tables and kept current."""

from __future__ import annotations

from pathlib import Path

import pytest
from PIL import Image

from canergy.cli import main
from canergy.core import hardened
from canergy.core.inputs import PowerLoss
from canergy.core.table import ANY, cell
from canergy.rules_doc import TABLES, diagram_source, figure_name, markdown, source_hash

DOCS = Path(__file__).resolve().parents[1] / "docs"
REGENERATE = "stale: run `canergy rules --docs docs` and commit"


def test_reference_is_current() -> None:
    assert (DOCS / "transitions.md").read_text() == markdown(), REGENERATE


@pytest.mark.parametrize("table", TABLES, ids=figure_name)
def test_figure_is_current(table) -> None:  # type: ignore[no-untyped-def]
    with Image.open(DOCS / "figures" / figure_name(table)) as image:
        assert image.info.get("Description") == source_hash(table), REGENERATE


def test_a_changed_cell_changes_the_reference_and_the_figure() -> None:
    changed = hardened.CLIENT.with_cells(
        cell(ANY, PowerLoss, hardened.restart_client, to=hardened.HOLDING)
    )
    assert "AWAIT_COMMAND -> AWAIT_COMMAND: INTENTION" in diagram_source(hardened.CLIENT)
    assert source_hash(changed) != source_hash(hardened.CLIENT)
    assert markdown([changed]) != markdown([hardened.CLIENT])


def test_one_command_writes_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["rules", "--docs", str(tmp_path)]) == 0
    assert (tmp_path / "transitions.md").read_text() == markdown()
    for table in TABLES:
        with Image.open(tmp_path / "figures" / figure_name(table)) as image:
            assert image.info["Description"] == source_hash(table)
    assert main(["rules", "--docs", str(tmp_path / "missing")]) == 2
