"""``canergy dump``, ``canergy decode`` and ``canergy audit``: looking at canergy traffic."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any, TextIO

import can

from canergy.auth.capture import CaptureAuth, verified
from canergy.auth.keys import load_key
from canergy.cli_args import COUNT_MAX, bounded_int, energy, id_base, node_ids
from canergy.codec import Codec
from canergy.inspect.audit import Auditor
from canergy.inspect.captures import CaptureError, read_file, read_text
from canergy.inspect.frames import Described
from canergy.inspect.render import line
from canergy.live.bus_args import add_bus_flags, open_bus


def _auth_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--auth",
        type=Path,
        metavar="KEYFILE",
        help="check the MACs of authenticated frames with this key (the master key, or a "
        "node's own key for its frames): mac ok / MAC BAD; without it they show mac ?",
    )


def _capture_auth(args: argparse.Namespace, codec: Codec) -> CaptureAuth:
    return CaptureAuth(codec, load_key(args.auth) if args.auth is not None else None)


def _view_flags(p: argparse.ArgumentParser) -> None:
    _auth_flag(p)
    p.add_argument(
        "--audit",
        action="store_true",
        help="run the audit alongside: a frame it flags (a forgery, a second supervisor's "
        "interleaved sequence...) gets a line starting with !! under it",
    )
    p.add_argument("--nodes", type=node_ids, help="only frames of these node ids, e.g. 1-5,9")
    p.add_argument("--hide-foreign", action="store_true", help="hide frames that are not canergy's")
    p.add_argument("--json", action="store_true", help="one JSON object per frame")
    p.add_argument(
        "--color",
        choices=["auto", "always", "never"],
        default="auto",
        help="colour per transaction (auto: only on a terminal)",
    )


def add_parsers(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    d = sub.add_parser(
        "dump",
        help="candump-style live view with every canergy frame decoded",
        description="Print each frame like candump (timestamp, interface, ID, DLC, bytes) and "
        "what it means to canergy. Stop with Ctrl-C.",
    )
    add_bus_flags(d)
    _view_flags(d)
    d.add_argument(
        "-n", "--count", type=bounded_int(1, COUNT_MAX), help="exit after this many frames"
    )
    c = sub.add_parser(
        "decode",
        help="decode a capture: candump text from stdin or any python-can log file",
        description="Decode candump output (default, -ta, -L/-l formats) from FILE or stdin "
        "('-'), or .asc/.blf/.csv/.trc/.mf4 files through python-can.",
    )
    c.add_argument("file", nargs="?", default="-", help="capture file, or - for stdin")
    c.add_argument("--id-base", type=id_base, default=Codec().id_base)
    _view_flags(c)
    a = sub.add_parser(
        "audit",
        help="rebuild transactions from a capture and check the protocol and passivity",
        description="Replay a capture through a passive observer; exit 1 when the capture shows a "
        "protocol or passivity violation, naming the frame.",
    )
    a.add_argument("file", help="capture file, or - for stdin")
    a.add_argument("--initial", type=energy, help="the supervisor's initial budget, e.g. 10J")
    a.add_argument(
        "--reordered",
        action="store_true",
        help="the capture was taken behind a channel that reorders frames (e.g. canergy demo): "
        "frames of older transactions are counted as stale, not as violations",
    )
    a.add_argument("--id-base", type=id_base, default=Codec().id_base)
    a.add_argument("--json", action="store_true", help="the report as JSON")
    _auth_flag(a)


def _garbage(number: int, text: str, reason: str) -> None:
    print(f"line {number}: skipped ({reason}): {text[:80]}", file=sys.stderr)


def _frames(path: str) -> Iterator[can.Message]:
    if path == "-":
        return read_text(sys.stdin, _garbage)
    return read_file(Path(path), _garbage)


def _show(
    described: Iterable[Described], args: argparse.Namespace, out: TextIO, live: bool = False
) -> None:
    colour = args.color == "always" or (args.color == "auto" and out.isatty())
    auditor = Auditor() if args.audit else None
    for d in described:
        flagged = _audited(auditor, d)
        if args.hide_foreign and d.message is None and not d.ours:
            continue
        if args.nodes is not None and (d.message is None or d.message.node not in args.nodes):
            continue
        out.write((json.dumps(d.as_json()) if args.json else line(d, colour=colour)) + "\n")
        for here, v in flagged:
            assert auditor is not None
            many = auditor.channels
            where = f"{here}{v.channel}/{v.node}: " if many and v.node is not None else here
            out.write(
                json.dumps({"violation": v.as_json(many)}) if args.json else f"!! {where}{v.what}"
            )
            out.write("\n")
        if live:
            out.flush()


def _audited(auditor: Auditor | None, d: Described) -> list[tuple[str, Any]]:
    """The audit's new violations once ``d`` is fed, each with where it points ("" for this
    frame; some are decided later and concern an earlier one). A MAC that failed moves nothing."""
    if auditor is None:
        return []
    before = len(auditor.violations)
    auditor.feed(replace(d, message=None, crc_ok=None) if d.mac == "BAD" else d)
    return [
        ("" if v.frame == auditor.frames else f"frame {v.frame}: ", v)
        for v in auditor.violations[before:]
    ]


def run_decode(args: argparse.Namespace) -> int:
    codec = Codec(args.id_base)
    auth = _capture_auth(args, codec)
    try:
        _show((auth.describe(f) for f in _frames(args.file)), args, sys.stdout)
    except CaptureError as exc:
        print(f"canergy decode: error: {exc}", file=sys.stderr)
        return 2
    return 0


def run_dump(args: argparse.Namespace) -> int:
    codec = Codec(args.id_base)
    auth = _capture_auth(args, codec)
    bus = open_bus(args, [])
    channel = getattr(args, "channel", None)
    stop = False

    def request_stop(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, request_stop)
        signal.signal(signal.SIGTERM, request_stop)

    def frames() -> Iterator[Described]:
        received = 0
        while not stop and (args.count is None or received < args.count):
            frame = bus.recv(timeout=0.2)
            if frame is not None:
                received += 1
                if frame.channel is None:  # not every interface names it: the one opened
                    frame.channel = channel
                yield auth.describe(frame)

    try:
        _show(frames(), args, sys.stdout, live=True)
    finally:
        bus.shutdown()
    return 0


def run_audit(args: argparse.Namespace) -> int:
    codec = Codec(args.id_base)
    auth = _capture_auth(args, codec)
    auditor = Auditor(initial=args.initial, reordered=args.reordered)
    try:
        described = [auth.describe(frame) for frame in _frames(args.file)]
    except CaptureError as exc:
        print(f"canergy audit: error: {exc}", file=sys.stderr)
        return 2
    if auth.key is not None:  # what the receivers took: forged and unauthenticated frames out
        bad = sum(d.mac == "BAD" for d in described)
        described = verified(described)
        print(f"canergy audit: {bad} frame(s) failed their MAC and move nothing", file=sys.stderr)
    for d in described:
        auditor.feed(d)
    auditor.finish()
    report = auditor.report()
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_audit(report)
    return 0 if report["passive"] else 1


def _print_audit(report: dict[str, Any]) -> None:
    print(
        f"canergy audit: {report['frames']} frames, "
        f"{report['foreign_frames']} foreign, {report['damaged_frames']} damaged, "
        f"{report['stale_frames']} stale"
    )
    wide = max([4, *map(len, report["nodes"])])  # can1/5 in a capture of several channels
    print(
        f"{'node':>{wide}} {'seen':>5} {'commit':>6} {'abort':>5} {'open':>4} {'resent':>6} "
        f"{'granted J':>10} {'returned J':>10} {'holdable<= J':>12}"
    )
    for node, r in report["nodes"].items():
        hold = "" if r["holdable_max_uj"] is None else f"{r['holdable_max_uj'] / 1e6:.3f}"
        print(
            f"{node:>{wide}} {r['transactions_seen']:>5} {r['committed']:>6} {r['aborted']:>5} "
            f"{r['unresolved']:>4} {r['resent_intentions']:>6} {r['granted_uj'] / 1e6:>10.3f} "
            f"{r['returned_uj'] / 1e6:>10.3f} {hold:>12}"
        )
    for v in report["violations"]:
        where = f"frame {v['frame']}" + (f" ({v['timestamp']:.6f})" if v["timestamp"] else "")
        print(f"VIOLATION {where}: {v['what']}" + (f"\n    {v['line']}" if v["line"] else ""))
    print("verdict: " + ("no violation seen" if report["passive"] else "VIOLATIONS (exit 1)"))


COMMANDS = {"dump": run_dump, "decode": run_decode, "audit": run_audit}
