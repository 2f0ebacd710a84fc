"""``canergy bridge``: a fault-injecting bridge between two CAN buses (``canergy.bridge``)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from datetime import datetime
from pathlib import Path
from typing import Any

from canergy.argtypes import add_duration, argument, duration_or_zero, probability, seed
from canergy.bridge.link import Bridge
from canergy.bridge.schedule import FaultSchedule, Partition
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.cli.summaries import SUMMARIES
from canergy.faults import FaultProfile
from canergy.inspect.candump import FrameLog, log_path, open_log
from canergy.live.atomic import check_writable_dir, same_file, write_json_atomic
from canergy.units import format_duration

SIDES = ("bus1", "bus2")
"""The flag prefixes of the two buses, as python-can's own bridge (``python -m can.bridge``)."""


def partition(text: str) -> Partition:
    return argument(Partition.parse, text)


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "bridge",
        help=SUMMARIES["bridge"],
        description="Carry every frame received on one bus to the other (the flags of each as "
        "python -m can.bridge takes them: --bus1-interface, --bus1-channel, ..., --bus2-...), "
        "through seeded faults: loss, duplication, reordering, delay, bit flips and partitions "
        "(the link cut for a time). The same --seed and the same frames give the same "
        "decisions. A status line on stderr every --status-period, --status-file as JSON, "
        "--log a capture of both buses. Stop with Ctrl-C (SIGINT) or SIGTERM.",
    )
    for side in SIDES:
        add_bus_flags(p, id_base_flag=False, prefix=side)
    f = p.add_argument_group("faults (each direction on its own, from the same seed)")
    f.add_argument("--seed", type=seed, default=0, help="0..2**32-1 (default 0)")
    f.add_argument("--loss", type=probability, default=0.0, help="frame loss probability")
    f.add_argument(
        "--duplicate", type=probability, default=0.0, help="probability a frame arrives twice"
    )
    f.add_argument(
        "--reorder",
        type=probability,
        default=0.0,
        help="probability a frame is held back behind later ones (by up to --reorder-delay)",
    )
    f.add_argument(
        "--corrupt", type=probability, default=0.0, help="probability one data bit flips"
    )
    f.add_argument(
        "--delay",
        type=duration_or_zero,
        default=0,
        metavar="TIME",
        help="extra delay of every frame, uniform in --delay +- --jitter (default 0)",
    )
    f.add_argument(
        "--jitter",
        type=duration_or_zero,
        default=0,
        metavar="TIME",
        help="spread of the delay, at most --delay (default 0)",
    )
    add_duration(f, "--reorder-delay", 20_000, "the longest a reordered frame is held back")
    f.add_argument(
        "--partition",
        type=partition,
        action="append",
        default=[],
        metavar="AT+FOR",
        help="cut the link both ways from AT after the start for FOR, e.g. 2s+3s (repeatable)",
    )
    p.add_argument("--status-file", type=Path, help="the counts as JSON, every --status-period")
    add_duration(p, "--status-period", 1_000_000, "time between status lines (and files)")
    p.add_argument(
        "--log",
        type=Path,
        metavar="FILE",
        help="capture both buses as the bridge sees them, each frame under its bus's channel "
        "(what it received there, what it sent there), in the format the extension names "
        "(python-can's writers: .log candump, .asc, .blf, .csv, .trc...)",
    )
    p.set_defaults(run=run)


def profile(args: argparse.Namespace) -> FaultProfile:
    """The faults the flags give; ``ValueError`` naming the flags for a jitter above the delay."""
    if args.jitter > args.delay:
        raise ValueError(
            f"--jitter {format_duration(args.jitter)} is above --delay "
            f"{format_duration(args.delay)}: a frame cannot arrive before it was sent"
        )
    return FaultProfile(
        loss=args.loss,
        duplicate=args.duplicate,
        reorder=args.reorder,
        corrupt=args.corrupt,
        delay_us=args.delay,
        jitter_us=args.jitter,
        reorder_delay_us=args.reorder_delay,
    )


def _where(args: argparse.Namespace, side: str) -> str:
    """The side's channel as given (its prefix when none: the interface's default)."""
    channel = getattr(args, f"{side}_channel", None)
    return str(channel) if channel else side


def _check(args: argparse.Namespace) -> tuple[str, str]:
    """The two buses are two (a bridge from a bus to itself would echo every frame forever)
    and the files can be written; the buses' names."""
    names = (_where(args, SIDES[0]), _where(args, SIDES[1]))
    keys = [
        (getattr(args, f"{s}_interface", None), getattr(args, f"{s}_channel", None)) for s in SIDES
    ]
    if keys[0] == keys[1] and keys[0][1] is not None:
        raise ValueError(
            f"--bus1-channel and --bus2-channel name the same bus {names[0]!r} on the same "
            "interface: a bridge carries frames between two buses"
        )
    if names[0] == names[1]:  # the capture and the status tell the sides by name
        names = (f"{SIDES[0]}:{names[0]}", f"{SIDES[1]}:{names[1]}")
    if args.status_file is not None:
        check_writable_dir(args.status_file, "--status-file")
        if args.log is not None and same_file(args.status_file, args.log):
            raise ValueError("--status-file and --log name the same file; give each its own")
    return names


def status_line(status: dict[str, Any]) -> str:
    """One line of counts, e.g. ``canergy bridge: vcan0>vcan1 120 frames, 110 forwarded, lost
    12, duplicated 2, ...; vcan1>vcan0 ...``."""
    parts = []
    for name, c in status["directions"].items():
        faults = ", ".join(
            f"{k} {c[k]}"
            for k in (
                *("lost", "duplicated", "reordered", "corrupted", "partitioned"),
                *("cut_in_flight", "send_errors"),
            )
            if c[k]
        )
        parts.append(
            f"{name} {c['frames']} frames, {c['forwarded']} forwarded"
            + (f", {faults}" if faults else "")
        )
    return f"canergy bridge: {status['uptime_s']:.1f} s: " + "; ".join(parts)


def run(args: argparse.Namespace) -> int:
    names = _check(args)
    schedule = FaultSchedule(profile(args), args.seed, args.partition)
    target = log_path(args.log, datetime.now()) if args.log is not None else None
    stop = threading.Event()

    def request_stop(signum: int, frame: object) -> None:
        stop.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, request_stop)
        signal.signal(signal.SIGTERM, request_stop)
    buses: list[Any] = []
    capture: FrameLog | None = None
    bridge = None
    try:
        for side in SIDES:
            buses.append(open_bus(args, [], prefix=side))
        if target is not None:
            capture, path = open_log(target[0], names[0], auto=target[1])
            print(f"canergy bridge: capturing both buses to {path}", file=sys.stderr)
        bridge = Bridge((buses[0], buses[1]), schedule, names=names, capture=capture)
        print(f"canergy bridge: {names[0]} <-> {names[1]}, seed {args.seed}", file=sys.stderr)
        report = _reporter(args, bridge)
        bridge.run(stop.is_set, report)
        report(None)
    finally:
        if bridge is not None:
            bridge.close()
        try:
            if capture is not None:
                capture.stop()
        finally:
            for bus in buses:
                bus.shutdown()
    return 0


def _reporter(args: argparse.Namespace, bridge: Bridge) -> Any:
    """``report(now_us)``: the status line and file once a period; ``report(None)``: now."""
    next_at = [bridge.clock() + args.status_period]

    def report(now: int | None) -> None:
        if now is not None and now < next_at[0]:
            return
        next_at[0] = bridge.clock() + args.status_period
        status = bridge.status()
        print(status_line(status), file=sys.stderr, flush=True)
        if args.status_file is not None:
            write_json_atomic(args.status_file, status, fsync=False)

    return report
