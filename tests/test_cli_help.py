"""Every command's ``--help`` as it was before the CLI became one module per command
(``tests/data/cli_help``): the move changed no command, flag or help text. A flag changed on
purpose updates its file in the same commit (``python tests/test_cli_help.py --update``).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import sys
from pathlib import Path

import pytest

from canergy.cli import build_parser, main

HELP = Path(__file__).parent / "data" / "cli_help"
INTERFACES = re.compile(r"\{[a-z0-9_,]*socketcan[a-z0-9_,]*\}")
"""python-can's interface list, which its plugins extend: not canergy's to compare."""


def commands() -> list[str]:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return list(sub.choices)


def shown(command: str, monkeypatch: pytest.MonkeyPatch | None = None) -> str:
    if monkeypatch is not None:
        monkeypatch.setenv("COLUMNS", "100")
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as ended:
        main([command, "--help"] if command else ["--help"])
    assert ended.value.code == 0
    return INTERFACES.sub("{INTERFACES}", out.getvalue())


def test_every_command_has_its_help_file_and_no_file_is_left_over() -> None:
    files = {p.stem for p in HELP.glob("*.txt")}
    assert files == {"canergy", *commands()}


@pytest.mark.parametrize("command", ["", *commands()])
def test_help_is_what_it_was(command: str, monkeypatch: pytest.MonkeyPatch) -> None:
    expected = (HELP / f"{command or 'canergy'}.txt").read_text()
    assert shown(command, monkeypatch) == INTERFACES.sub("{INTERFACES}", expected)


if __name__ == "__main__" and sys.argv[1:] == ["--update"]:
    import os

    os.environ["COLUMNS"] = "100"
    for name in ["", *commands()]:
        (HELP / f"{name or 'canergy'}.txt").write_text(shown(name))
