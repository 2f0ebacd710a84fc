"""The site's CLI reference (docs/_ext/cli_reference.py, run by every build of the site) names
every command and every option of the parsers, each under its command's heading."""

from __future__ import annotations

import argparse
import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType

import pytest

from canergy.cli import build_parser

GENERATOR = Path(__file__).resolve().parents[1] / "docs" / "_ext" / "cli_reference.py"


def generator() -> ModuleType:
    spec = importlib.util.spec_from_file_location("cli_reference", GENERATOR)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("cli_reference", module)
    spec.loader.exec_module(module)
    return module


def sections(text: str) -> dict[str, str]:
    """The reference's text under each ``(anchor)=`` label."""
    parts = re.split(r"^\((cli-[a-z0-9-]+)\)=$", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def options(parser: argparse.ArgumentParser) -> list[str]:
    return [name for action in parser._actions for name in action.option_strings]


def subparsers() -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


@pytest.fixture(scope="module")
def reference() -> dict[str, str]:
    return sections(generator().render())


def test_every_command_has_its_section(reference: dict[str, str]) -> None:
    assert set(reference) == {
        "cli-canergy",
        "cli-firmware-model",
        "cli-firmware-model-drive",
        *(f"cli-{name}" for name in subparsers()),
    }


@pytest.mark.parametrize("name", sorted(subparsers()))
def test_every_flag_of_a_command_is_in_its_section(name: str, reference: dict[str, str]) -> None:
    section = reference[f"cli-{name}"]
    assert f"## `canergy {name}`" in section
    missing = [flag for flag in options(subparsers()[name]) if f"`{flag}" not in section]
    assert not missing, f"canergy {name}: {missing} not in the CLI reference"


def test_the_emulators_flags_are_in_their_sections(reference: dict[str, str]) -> None:
    from firmware_model.__main__ import build_parser as node_parser
    from firmware_model.drive.__main__ import build_parser as drive_parser

    for anchor, parser in (
        ("cli-firmware-model", node_parser()),
        ("cli-firmware-model-drive", drive_parser()),
    ):
        missing = [flag for flag in options(parser) if f"`{flag}" not in reference[anchor]]
        assert not missing, f"{anchor}: {missing}"


def test_the_reference_is_added_to_its_page_only() -> None:
    module = generator()
    page, other = ["intro\n"], ["intro\n"]
    module._append(None, module.PAGE, page)
    module._append(None, "index", other)
    assert "## `canergy supervisor`" in page[0] and other == ["intro\n"]


def test_markdown_in_help_text_is_shown_as_written() -> None:
    assert generator().escape("a *b* [c](d) `e` <f>") == r"a \*b\* \[c\](d) \`e\` \<f\>"
