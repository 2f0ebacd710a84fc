"""The CLI reference, generated from the argparse parsers at build time.

``render()`` writes every command of ``canergy.cli.build_parser()`` (and the emulators'
parsers) as markdown: its description, usage and each option with its help. As a Sphinx
extension it appends that text to the page ``reference/cli`` whenever the site is built, so a
renamed flag shows up without editing a page.
"""

from __future__ import annotations

import argparse
import os
import re
from collections.abc import Iterator
from typing import Any

PAGE = "reference/cli"
WIDTH = "100"
_SPECIAL = re.compile(r"([\\`*_{}\[\]<>#|~$!])")


def escape(text: str) -> str:
    """Text shown as written: markdown's special characters escaped."""
    return _SPECIAL.sub(r"\\\1", text)


def parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    """(anchor, parser) of every documented command: canergy, its subcommands, the emulators."""
    from canergy.cli import build_parser
    from firmware_model.__main__ import build_parser as node_parser
    from firmware_model.drive.__main__ import build_parser as drive_parser

    top = build_parser()
    found = [("cli-canergy", top)]
    for name, sub in subcommands(top):
        found.append((f"cli-{name}", sub))
    found += [("cli-firmware-model", node_parser()), ("cli-firmware-model-drive", drive_parser())]
    return found


def subcommands(parser: argparse.ArgumentParser) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            yield from action.choices.items()


def _option(formatter: argparse.HelpFormatter, action: argparse.Action) -> str:
    if action.option_strings:
        metavar = ""
        if action.nargs != 0:
            metavar = " " + formatter._format_args(action, action.dest.upper())
        names = ", ".join(f"`{name}{metavar}`" for name in action.option_strings)
    else:
        names = f"`{formatter._metavar_formatter(action, action.dest)(1)[0]}`"
    text = formatter._expand_help(action) if action.help else ""
    return f"{names}\n: {escape(' '.join(text.split())) or '(no help text)'}\n"


def _command(anchor: str, parser: argparse.ArgumentParser) -> str:
    formatter = parser._get_formatter()
    lines = [f"({anchor})=", f"## `{parser.prog}`", ""]
    if parser.description:
        lines += [escape(" ".join(parser.description.split())), ""]
    lines += ["```text", parser.format_usage().strip(), "```", ""]
    for group in parser._action_groups:
        actions = [a for a in group._group_actions if a.help != argparse.SUPPRESS]
        actions = [a for a in actions if not isinstance(a, argparse._SubParsersAction)]
        if not actions:
            continue
        lines += [f"**{escape(group.title or 'options')}**", ""]
        if group.description:
            lines += [escape(" ".join(group.description.split())), ""]
        lines += [_option(formatter, a) for a in actions]
    if parser.epilog:
        lines += [escape(" ".join(parser.epilog.split())), ""]
    for name, _ in subcommands(parser):
        lines.append(f"- [`{parser.prog} {name}`](#cli-{name})")
    return "\n".join(lines) + "\n"


def render() -> str:
    """The reference of every command as markdown (argparse's help at 100 columns)."""
    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        return "\n".join(_command(anchor, parser) for anchor, parser in parsers())
    finally:
        if before is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = before


def _append(app: Any, docname: str, source: list[str]) -> None:
    if docname == PAGE:
        source[0] += "\n" + render()


def _always_outdated(app: Any, env: Any, added: Any, changed: Any, removed: Any) -> list[str]:
    return [PAGE]


def setup(app: Any) -> dict[str, Any]:
    app.connect("source-read", _append)
    app.connect("env-get-outdated", _always_outdated)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
