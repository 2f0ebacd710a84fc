"""``canergy decode``: decode a capture, candump text from stdin or any python-can log
file."""

from __future__ import annotations

import argparse
import sys

from canergy.argtypes import id_base
from canergy.cli.shared.capture import (
    capture_auth,
    capture_frames,
    show,
    view_flags,
)
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.inspect.captures import CaptureError


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    c = sub.add_parser(
        "decode",
        help=SUMMARIES["decode"],
        description="Decode candump output (default, -ta, -L/-l formats) from FILE or stdin "
        "('-'), or .asc/.blf/.csv/.trc/.mf4 files through python-can.",
    )
    c.add_argument("file", nargs="?", default="-", help="capture file, or - for stdin")
    c.add_argument("--id-base", type=id_base, default=Codec().id_base)
    view_flags(c)
    c.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    codec = Codec(args.id_base)
    auth = capture_auth(args, codec)
    try:
        show((auth.describe(f) for f in capture_frames(args.file)), args, sys.stdout)
    except CaptureError as exc:
        print(f"canergy decode: error: {exc}", file=sys.stderr)
        return 2
    return 0
