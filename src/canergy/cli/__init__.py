"""The ``canergy`` command line: one module per command, named after it (``canergy.cli.dump``
for ``canergy dump``), each adding its parser and its ``run``; flag groups that several commands
share are in ``canergy.cli.shared``. A command's module is imported only when it runs (its
summary for ``canergy --help`` is in ``canergy.cli.summaries``), so one command's missing extra
or broken import touches no other."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Iterable, Sequence
from types import ModuleType

from canergy import __version__
from canergy.cli.summaries import SUMMARIES
from canergy.errors import BusOpenError
from canergy.extras import MissingExtra


def command_module(name: str) -> ModuleType:
    """The module of command ``name`` (``canergy.cli.<name>``), imported now."""
    return importlib.import_module(f"canergy.cli.{name}")


def build_parser(commands: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The parser with ``commands`` (default: every one) complete; the others are listed by
    their summaries only, and their modules are not imported."""
    full = set(SUMMARIES if commands is None else commands)
    parser = argparse.ArgumentParser(
        prog="canergy",
        description="Passive energy budget transactions over CAN (Groothuis & Stramigioli).",
    )
    parser.add_argument("--version", action="version", version=f"canergy {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, summary in SUMMARIES.items():
        if name in full:
            command_module(name).add(sub)
        else:
            sub.add_parser(name, help=summary)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    words = list(sys.argv[1:] if argv is None else argv)
    try:  # only the command named first is imported: `canergy dbc` loads no bus, core or C
        parser = build_parser(words[:1])
    except MissingExtra as exc:
        print(f"canergy {words[0]}: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(words)
    try:
        return int(args.run(args))
    except BrokenPipeError:  # e.g. `canergy demo | head`: stop quietly like other CLI tools
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (ValueError, OSError, BusOpenError) as exc:  # bad values, paths, buses
        print(f"canergy {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MissingExtra as exc:  # e.g. canergy plot: needs matplotlib: pip install ...
        print(f"canergy {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
