"""The ``canergy`` command line: one module per command, named after it (``canergy.cli.dump``
for ``canergy dump``), each adding its parser and its ``run``; flag groups that several commands
share are in ``canergy.cli.shared``."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from types import ModuleType

from canergy import __version__
from canergy.cli import (
    audit,
    bench,
    bridge,
    check,
    dbc,
    decode,
    demo,
    dump,
    gateway,
    grant,
    keys,
    ledger,
    monitor,
    plot,
    prove,
    rules,
    simulate,
    supervisor,
    sweep,
)
from canergy.extras import MissingExtra
from canergy.live.bus_args import BusOpenError

COMMANDS: tuple[ModuleType, ...] = (
    demo,
    check,
    prove,
    dbc,
    rules,
    supervisor,
    grant,
    gateway,
    ledger,
    simulate,
    sweep,
    dump,
    decode,
    audit,
    monitor,
    plot,
    keys,
    bench,
    bridge,
)
"""In the order ``canergy --help`` lists them."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="canergy",
        description="Passive energy budget transactions over CAN (Groothuis & Stramigioli).",
    )
    parser.add_argument("--version", action="version", version=f"canergy {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
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
