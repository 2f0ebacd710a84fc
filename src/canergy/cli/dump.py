"""``canergy dump``: a candump-style live view with every canergy frame decoded."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

from canergy.argtypes import COUNT_MAX, argument, bounded_int
from canergy.cli.shared.bus_flags import add_bus_flags, bus_where

# dump's bus opens with CAN FD on, or for classic CAN where the interface refuses FD
from canergy.cli.shared.bus_flags import open_receiving_bus as open_bus
from canergy.cli.shared.capture import (
    capture_auth,
    show,
    view_flags,
)
from canergy.cli.summaries import SUMMARIES
from canergy.codec import Codec
from canergy.inspect.candump import ChannelFilters, FrameLog, log_path, open_log
from canergy.inspect.frames import Described
from canergy.inspect.render import STAMP_MODES, Stamps


def channel_filters(text: str) -> ChannelFilters:
    """candump's ``CHANNEL[,FILTER[,FILTER...]]``."""
    return argument(ChannelFilters.parse, text)


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    d = sub.add_parser(
        "dump",
        help=SUMMARIES["dump"],
        description="Print each frame like candump (timestamp, interface, ID, DLC, bytes) and "
        "what it means to canergy. CAN FD frames are received without --fd where the "
        "interface supports FD. Stop with Ctrl-C.",
        epilog="Filters (as candump's, hex): ID:MASK passes a frame when received_id & MASK == "
        "ID & MASK, ID~MASK when not; an ID of more than 3 digits (or above 7FF) filters 29-bit "
        "frames only. E.g. vcan0,0CE00100:1FFFFF00 every INTENTION, vcan0,0CE00005:1FFFF0FF "
        "every canergy frame of node 5 (the default --id-base). Of several filters any one "
        "passes a frame (with j: all must). The interface (or the kernel) filters where it can, "
        "and dump checks again; -l/--log log what the filters pass.",
    )
    d.add_argument(
        "channel_filters",
        nargs="?",
        type=channel_filters,
        metavar="CHANNEL[,FILTER...]",
        help="the channel (as -c) with candump's filters, e.g. vcan0,0CE00100:1FFFFF00,701~7FF",
    )
    add_bus_flags(d, fd_default=True)
    view_flags(d)
    d.add_argument(
        "-n", "--count", type=bounded_int(1, COUNT_MAX), help="exit after this many frames"
    )
    d.add_argument(
        "-t",
        "--timestamp",
        choices=STAMP_MODES,
        default="a",
        help="as candump -t: a absolute (default), d since the previous frame shown, z since "
        "the first one, A absolute local date and time",
    )
    log = d.add_mutually_exclusive_group()
    log.add_argument(
        "-l",
        dest="log",
        action="store_const",
        const=Path("."),
        help="log every frame received (also those --nodes/--hide-foreign hide) to "
        "candump-YYYY-MM-DD_HHMMSS.log here, in candump -l's format",
    )
    log.add_argument(
        "--log",
        type=Path,
        metavar="FILE",
        help="log every frame received to FILE in the format its extension names "
        "(python-can's writers: .log candump, .asc, .blf, .csv, .trc, .txt, .db...; .gz "
        "compressed); a directory: candump's file name in it",
    )
    d.set_defaults(run=run)


def _channel(args: argparse.Namespace) -> None:
    """The positional CHANNEL sets -c (the same channel twice is no conflict)."""
    spec: ChannelFilters | None = args.channel_filters
    if spec is None:
        return
    given = getattr(args, "channel", None)
    if given is not None and given != spec.channel:
        raise ValueError(f"two channels: -c {given} and {spec.channel}; give one")
    args.channel = spec.channel


def run(args: argparse.Namespace) -> int:
    _channel(args)
    spec: ChannelFilters = args.channel_filters or ChannelFilters("")
    codec = Codec(args.id_base)
    auth = capture_auth(args, codec)
    stamps = Stamps(args.timestamp)
    target = log_path(args.log, datetime.now()) if args.log is not None else None
    bus = open_bus(args, spec.hardware())
    log: FrameLog | None = None
    stop = False

    def request_stop(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    try:
        channel, interface = bus_where(args)
        if target is not None:
            log, path = open_log(target[0], channel or "can0", auto=target[1])
            print(f"canergy dump: logging every frame received to {path}", file=sys.stderr)
        where = f"{channel or 'the default channel'} ({interface or 'default interface'})"
        print(f"canergy dump: waiting on {where}...", file=sys.stderr, flush=True)
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, request_stop)
            signal.signal(signal.SIGTERM, request_stop)

        def frames() -> Iterator[Described]:
            received = 0
            while not stop and (args.count is None or received < args.count):
                frame = bus.recv(timeout=0.2)
                if frame is None or not spec.accepts(frame):
                    continue
                received += 1
                if frame.channel is None:  # not every interface names it: the one opened
                    frame.channel = channel
                if log is not None:
                    log.on_message_received(frame)
                yield auth.describe(frame)

        show(frames(), args, sys.stdout, live=True, stamps=stamps)
    finally:
        try:
            if log is not None:
                log.stop()
        finally:
            bus.shutdown()
    return 0
