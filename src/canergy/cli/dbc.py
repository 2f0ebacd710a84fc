"""``canergy dbc``: write the DBC describing canergy's frames."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from canergy.argtypes import (
    id_base,
)
from canergy.cli.summaries import SUMMARIES


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("dbc", help=SUMMARIES["dbc"])
    p.add_argument("-o", "--output", type=Path, help="file to write (default: stdout)")
    p.add_argument(
        "--auth",
        choices=["fd", "classic"],
        help="describe an authenticated layout: fd (CAN FD frames with FV and a 64-bit MAC) or "
        "classic (each message followed by a MAC frame)",
    )
    p.add_argument(
        "--id-base",
        type=id_base,
        default=None,
        help="29-bit identifier base, low 12 bits clear (default 0x0CE00000)",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canergy.codec import DEFAULT_ID_BASE
    from canergy.dbc import dbc_text

    text = dbc_text(DEFAULT_ID_BASE if args.id_base is None else args.id_base, args.auth)
    if args.output:
        args.output.write_bytes(text.encode())
    else:
        sys.stdout.write(text)
    return 0
