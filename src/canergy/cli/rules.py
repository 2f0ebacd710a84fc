"""``canergy rules``: print the transition tables; ``--docs DIR`` also writes the reference
and diagrams."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from canergy.cli.summaries import SUMMARIES
from canergy.extras import require


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "rules",
        help=SUMMARIES["rules"],
    )
    p.add_argument(
        "--docs",
        type=Path,
        metavar="DIR",
        help="write DIR/transitions.md and DIR/figures/states-*.png (the repo's: docs)",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canergy.rules_doc import markdown, write_docs

    if args.docs is None:
        sys.stdout.write(markdown())
        return 0
    require("plot")
    if not args.docs.is_dir():
        raise ValueError(f"--docs {args.docs}: not a directory")
    for path in write_docs(args.docs):
        print(f"wrote {path}")
    return 0
