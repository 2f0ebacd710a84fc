"""``canergy dump``: a candump-style live view with every canergy frame decoded."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Iterator

from canergy.argtypes import COUNT_MAX, bounded_int
from canergy.cli.shared.capture import (
    capture_auth,
    show,
    view_flags,
)
from canergy.codec import Codec
from canergy.inspect.frames import Described
from canergy.live.bus_args import add_bus_flags, open_bus


def add(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    d = sub.add_parser(
        "dump",
        help="candump-style live view with every canergy frame decoded",
        description="Print each frame like candump (timestamp, interface, ID, DLC, bytes) and "
        "what it means to canergy. Stop with Ctrl-C.",
    )
    add_bus_flags(d)
    view_flags(d)
    d.add_argument(
        "-n", "--count", type=bounded_int(1, COUNT_MAX), help="exit after this many frames"
    )
    d.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    codec = Codec(args.id_base)
    auth = capture_auth(args, codec)
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
        show(frames(), args, sys.stdout, live=True)
    finally:
        bus.shutdown()
    return 0
