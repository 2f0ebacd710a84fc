"""``canergy monitor``: the budgets on a bus (or in a replayed capture), full screen."""

from __future__ import annotations

import argparse
import contextlib
import locale
import math
import shutil
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

from canergy.argtypes import add_duration, argument, duration, energy
from canergy.auth.capture import CaptureAuth
from canergy.auth.keys import load_key
from canergy.cli.shared.bus_flags import add_bus_flags, open_receiving_bus
from canergy.cli.shared.capture import namer_of, others_flags
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.inspect.captures import read_file
from canergy.monitor.books import Books, BooksPoller, from_control, from_status_file
from canergy.monitor.feeds import Feed, LiveFeed, ReplayFeed
from canergy.monitor.model import MonitorModel
from canergy.monitor.render import Context, screen
from canergy.monitor.view import SORTS, View, parse_filter
from canergy.units import US_PER_S

SPEED_MAX = 1000.0


def speed(text: str) -> float:
    """A replay speed factor, 0.01 to 1000 (1: the capture's own pace)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a speed factor: {text[:24]!r}") from None
    if not (math.isfinite(value) and 0.01 <= value <= SPEED_MAX):
        raise argparse.ArgumentTypeError(f"speed {text[:24]!r} outside 0.01..{SPEED_MAX:g}")
    return value


def node_filter(text: str) -> tuple[str, frozenset[int] | None]:
    """``--nodes 3,5-7``: the text as typed and the ids it names."""
    return text.strip(), argument(parse_filter, text)


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "monitor",
        help=SUMMARIES["monitor"],
        description="One row per node: level, session, open transaction and its phase, "
        "commits/aborts/write-offs, returns, last outcome, lost and alarm flags; a header with "
        "frames/s, bus load, decode errors and the supervisor's usable budget. Rebuilt from the "
        "frames alone (it never sends one); add a running supervisor's books with "
        "--status-file or --control. Keys: q quit, p pause, / filter, s sort, arrows select, "
        "Enter raw frames, n step a paused replay.",
    )
    add_bus_flags(p, fd_default=True)
    p.add_argument(
        "--replay",
        type=Path,
        metavar="CAPTURE",
        help="replay a capture instead of reading a bus (candump text, .asc, .blf, .csv, .trc, "
        ".mf4 with the mf4 extra)",
    )
    pace = p.add_mutually_exclusive_group()
    pace.add_argument(
        "--speed",
        type=speed,
        help="--replay at this many times the capture's pace (default 1)",
    )
    pace.add_argument("--fast", action="store_true", help="--replay as fast as it reads")
    books = p.add_mutually_exclusive_group()
    books.add_argument(
        "--status-file", type=Path, help="a running supervisor's --status-file, polled"
    )
    books.add_argument(
        "--control", type=Path, metavar="SOCKET", help="a running supervisor's --control socket"
    )
    add_duration(p, "--books-period", 500_000, "how often to read the books")
    add_duration(p, "--lost-after", 3_000_000, "a node silent this long is flagged LOST")
    add_duration(p, "--refresh", 250_000, "how often the screen is redrawn")
    p.add_argument("--nodes", type=node_filter, help="show only these node ids, e.g. 3,5-7")
    p.add_argument("--sort", choices=SORTS, default="node", help="row order (key s cycles)")
    p.add_argument(
        "--full-scale",
        type=energy,
        metavar="ENERGY",
        help="level of a full bar, e.g. 2J (default: the highest level shown)",
    )
    p.add_argument(
        "--reordered",
        action="store_true",
        help="the frames went through a channel that reorders (canergy demo): the audit counts "
        "frames of older transactions as stale instead of raising an alarm",
    )
    p.add_argument(
        "--auth",
        type=Path,
        metavar="KEYFILE",
        help="check the MACs of authenticated frames with this key (bad ones count as errors)",
    )
    p.add_argument("--ascii", action="store_true", help="ASCII bars and sparklines only")
    others_flags(p)
    p.add_argument(
        "--once",
        action="store_true",
        help="no interactive screen: read the whole --replay (or the bus for --duration), "
        "print the screen once and exit",
    )
    p.add_argument(
        "--duration",
        type=duration,
        metavar="TIME",
        help="--once on a bus: listen this long (default 2s)",
    )
    p.set_defaults(run=run)


_BUS_ONLY = ("interface", "channel", "fd", "bus_kwargs", "timing")
"""Bus flags that mean nothing to a replay (python-can leaves absent ones out of ``args``)."""


def _check(args: argparse.Namespace) -> None:
    if args.replay is not None:
        given = [name for name in _BUS_ONLY if getattr(args, name, None)]
        if given:
            flags = ", ".join("--" + n.replace("_", "-") for n in given)
            raise ValueError(f"--replay reads a capture: not with {flags}")
        if args.status_file is not None or args.control is not None:
            raise ValueError("--status-file/--control show a running supervisor: not with --replay")
    elif args.speed is not None or args.fast:
        raise ValueError("--speed and --fast pace a --replay")
    if args.duration is not None and (not args.once or args.replay is not None):
        raise ValueError("--duration is for --once on a bus")
    if not args.once and not (sys.stdin.isatty() and sys.stdout.isatty()):
        raise ValueError("the screen needs a terminal; use --once to print it once")


def _unicode(args: argparse.Namespace) -> bool:
    """Block characters only where the terminal's encoding is UTF-8 (curses needs the
    locale set to draw them)."""
    if args.ascii:
        return False
    try:
        locale.setlocale(locale.LC_ALL, "")
    except locale.Error:  # a locale named in the environment but not installed
        return False
    return "utf" in locale.getpreferredencoding(False).lower().replace("-", "")


def _source(args: argparse.Namespace) -> str:
    if args.replay is not None:
        return f"replay {args.replay.name}"
    given = (getattr(args, "interface", None), getattr(args, "channel", None))
    where = " ".join(str(x) for x in given if x is not None)
    return where or "default bus (python-can configuration)"


def run(args: argparse.Namespace) -> int:
    _check(args)
    codec = Codec(args.id_base)
    auth = CaptureAuth(codec, load_key(args.auth)) if args.auth is not None else None
    model = MonitorModel(
        codec,
        bitrate=getattr(args, "bitrate", None),
        data_bitrate=getattr(args, "data_bitrate", None),
        lost_after_s=args.lost_after / US_PER_S,
        reordered=args.reordered,
        auth=auth,
        namer=namer_of(args),
    )
    lock = threading.Lock()
    view = View(sort=args.sort)
    if args.nodes is not None:
        view.filter_text, view.nodes = args.nodes
    ctx = Context(_source(args), "", args.full_scale, _unicode(args))
    if args.replay is not None:
        skipped: list[str] = []

        def garbage(number: int, text: str, reason: str) -> None:
            skipped.append(f"line {number}: {reason}")
            with lock:
                model.note("capture", f"{len(skipped)} line(s) skipped, {skipped[0]}")

        frames = read_file(args.replay, garbage)
        feed: Feed = ReplayFeed(
            frames, model, lock, None if args.once or args.fast else args.speed or 1.0
        )
        return _run(feed, model, lock, view, ctx, args, None)
    bus = open_receiving_bus(args, [])  # CAN FD on where the interface takes it
    try:
        return _run(
            LiveFeed(bus, model, lock), model, lock, view, ctx, args, _poller(args, model, lock)
        )
    finally:
        bus.shutdown()


def _poller(
    args: argparse.Namespace, model: MonitorModel, lock: threading.Lock
) -> BooksPoller | None:
    period = args.books_period / US_PER_S
    if args.status_file is not None:
        path = args.status_file

        def fetch(now: float) -> Books:
            return from_status_file(path, now)
    elif args.control is not None:
        socket = args.control

        def fetch(now: float) -> Books:
            return from_control(socket, now, timeout_s=max(1.0, period))
    else:
        return None

    def take(books: Books) -> None:
        with lock:
            model.set_books(books)

    return BooksPoller(fetch, period, take)


def _run(
    feed: Feed,
    model: MonitorModel,
    lock: threading.Lock,
    view: View,
    ctx: Context,
    args: argparse.Namespace,
    poller: BooksPoller | None,
) -> int:
    feed.start()
    if poller is not None:
        poller.start()
    try:
        if args.once:
            with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C: the screen as it is now
                _wait_once(feed, args)
            _print_once(feed, model, lock, view, ctx)
        else:
            from canergy.monitor import tui

            tui.run(feed, model, lock, view, ctx, args.refresh / US_PER_S)
    finally:
        if poller is not None:
            poller.stop()
        feed.stop()
    return 0


def _wait_once(feed: Feed, args: argparse.Namespace) -> None:
    if isinstance(feed, ReplayFeed):
        while not feed.done:
            time.sleep(0.02)
    else:
        time.sleep((args.duration or 2 * US_PER_S) / US_PER_S)


def _print_once(
    feed: Feed, model: MonitorModel, lock: threading.Lock, view: View, ctx: Context
) -> None:
    with lock:
        snap = model.snapshot(feed.now())
    width = shutil.get_terminal_size((160, 50)).columns
    lines = screen(
        snap,
        view,
        replace(ctx, state=feed.state(False)),
        width,
        len(snap.rows) + 12,
    )
    text = [t.rstrip() for t, _ in lines[:-1]]
    while text and not text[-1]:
        text.pop()
    print("\n".join(text))
