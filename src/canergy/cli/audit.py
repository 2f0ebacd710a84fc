"""``canergy audit``: rebuild transactions from a capture and check the protocol and
passivity."""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from typing import Any

from canergy.argtypes import energy, id_base
from canergy.auth.capture import verified
from canergy.cli.shared.capture import (
    auth_flag,
    capture_auth,
    capture_frames,
    namer_of,
    others_flags,
)
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.inspect.audit import Auditor
from canergy.inspect.captures import CaptureError
from canergy.inspect.others import protocol_of, tally


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    a = sub.add_parser(
        "audit",
        help=SUMMARIES["audit"],
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
    auth_flag(a)
    others_flags(a)
    a.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    codec = Codec(args.id_base)
    auth = capture_auth(args, codec)
    auditor = Auditor(initial=args.initial, reordered=args.reordered)
    try:
        described = [auth.describe(frame) for frame in capture_frames(args.file)]
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
    namer = namer_of(args)
    by = Counter(protocol_of(namer.named(d)) for d in described if not d.ours and not d.error_frame)
    report["foreign_by_protocol"] = dict(sorted(by.items()))
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_audit(report)
    return 0 if report["passive"] else 1


def _print_audit(report: dict[str, Any]) -> None:
    print(
        f"canergy audit: {report['frames']} frames, "
        f"{report['foreign_frames']} foreign{tally(report['foreign_by_protocol'])}, "
        f"{report['damaged_frames']} damaged, "
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
