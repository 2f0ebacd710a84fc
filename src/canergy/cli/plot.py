"""``canergy plot``: a capture's budgets per node over time and its messages, as a figure."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from canergy.argtypes import duration_or_zero, id_base, node_ids
from canergy.auth.capture import CaptureAuth, verified
from canergy.auth.keys import load_key
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.extras import require
from canergy.inspect.captures import CaptureError, read_file
from canergy.inspect.timeline import Timeline, timeline
from canergy.live.atomic import check_writable_dir
from canergy.units import US_PER_S

MAX_PANELS = 12
"""Nodes drawn when ``--node`` is not given (the lowest ids)."""


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "plot",
        help=SUMMARIES["plot"],
        description="Rebuild every node's books from a capture (as canergy audit does) and draw, "
        "per node, the energy granted (committed), returned and the most it can hold over "
        "time, with the audit's alarms, above a message-sequence chart. Any capture canergy "
        "decode reads; the format of the figure follows -o's suffix (.png, .svg, .pdf...).",
    )
    p.add_argument("file", type=Path, help="capture file")
    p.add_argument("-o", "--output", type=Path, required=True, help="figure to write, e.g. fig.png")
    p.add_argument(
        "--node",
        type=node_ids,
        help=f"only these node ids, e.g. 3,5-7 (default: all, at most the first {MAX_PANELS})",
    )
    p.add_argument(
        "--from",
        dest="start",
        type=duration_or_zero,
        metavar="TIME",
        help="show from this long after the first frame (e.g. 2.5s)",
    )
    p.add_argument(
        "--to", dest="end", type=duration_or_zero, metavar="TIME", help="show up to this time"
    )
    p.add_argument(
        "--reordered",
        action="store_true",
        help="the capture was taken behind a reordering channel (canergy demo), as for audit",
    )
    p.add_argument("--id-base", type=id_base, default=Codec().id_base)
    p.add_argument(
        "--auth",
        type=Path,
        metavar="KEYFILE",
        help="authenticated frames: leave out those whose MAC fails",
    )
    p.set_defaults(run=run)


def _check_output(path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    kinds = FigureCanvasAgg(Figure()).get_supported_filetypes()
    suffix = path.suffix.lower().lstrip(".")
    if suffix not in kinds:
        known = ", ".join(f".{k}" for k in sorted(kinds))
        raise ValueError(f"-o {path}: unknown figure format (known: {known})")
    check_writable_dir(path, "the figure")


def _nodes(tl: Timeline, wanted: tuple[int, ...] | None) -> list[str]:
    names = list(tl.nodes)
    if wanted is None:
        if len(names) > MAX_PANELS:
            print(
                f"canergy plot: {len(names)} nodes; drawing the first {MAX_PANELS} "
                "(choose with --node)",
                file=sys.stderr,
            )
        return names[:MAX_PANELS]
    chosen = [n for n in names if int(n.rpartition("/")[2]) in wanted]
    if not chosen:
        raise ValueError(f"--node: none of these nodes in the capture (it has {', '.join(names)})")
    return chosen


def run(args: argparse.Namespace) -> int:
    require("plot")  # before the capture is read: one line when matplotlib is missing
    _check_output(args.output)
    codec = Codec(args.id_base)
    auth = CaptureAuth(codec, load_key(args.auth) if args.auth is not None else None)
    skipped = 0

    def garbage(number: int, text: str, reason: str) -> None:
        nonlocal skipped
        skipped += 1

    try:
        described = [auth.describe(frame) for frame in read_file(args.file, garbage)]
    except CaptureError as exc:
        print(f"canergy plot: error: {exc}", file=sys.stderr)
        return 2
    if skipped:
        print(f"canergy plot: {skipped} line(s) that are not frames skipped", file=sys.stderr)
    if auth.key is not None:
        described = verified(described)
    tl = timeline(described, reordered=args.reordered)
    if not tl.nodes:
        raise ValueError(
            f"{args.file}: no canergy frames among its {len(described)} frame(s)"
            + (f" and {skipped} unreadable line(s)" if skipped else "")
            + f" (identifier block 0x{codec.id_base:08X}; another --id-base?)"
        )
    nodes = _nodes(tl, args.node)
    from canergy.inspect.capture_plot import draw

    verdict = f"{len(tl.violations)} audit alarm(s)" if tl.violations else "no audit alarm"
    title = f"{args.file.name}: {tl.frames:,} frames, {len(tl.nodes)} node(s), {verdict}"
    window = None
    if args.start is not None or args.end is not None:
        if not tl.timed:
            raise ValueError("--from/--to: this capture has no timestamps")
        window = (
            (args.start or 0) / US_PER_S,
            args.end / US_PER_S if args.end is not None else tl.end,
        )
        if window[0] >= tl.end:  # times run from the capture's first frame
            raise ValueError(
                f"--from/--to: the capture spans 0 s to {tl.end:.3f} s, nothing of it in that "
                "window"
            )
        if window[1] <= window[0]:
            raise ValueError("--to must be after --from")
    draw(tl, nodes, args.output, title, window)
    print(f"wrote {args.output}: {', '.join(f'node {n}' for n in nodes)}")
    return 0
