"""``python -m canergy.bench.sdo_server [bus flags] --node N``: the SDO baseline's server.

A python-canopen ``LocalNode`` with one writable UNSIGNED32 (0x2000:00) on the bus the flags
open, for ``canergy bench`` on a real interface to time SDO expedited writes against. It prints
``ready`` once it listens and serves until its standard input closes or it is terminated.
"""

from __future__ import annotations

import argparse
import signal
import sys
from collections.abc import Sequence

import canopen

from canergy.argtypes import bounded_int
from canergy.bench.live import sdo_dictionary
from canergy.cli.shared.bus_flags import add_bus_flags, open_bus
from canergy.errors import BusOpenError


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m canergy.bench.sdo_server")
    add_bus_flags(parser, id_base_flag=False)
    parser.add_argument("--node", type=bounded_int(1, 127), required=True, help="node id")
    args = parser.parse_args(argv)
    requests = [{"can_id": 0x600 + args.node, "can_mask": 0x7FF, "extended": False}]
    try:
        bus = open_bus(args, requests)
    except BusOpenError as exc:
        parser.exit(2, f"{parser.prog}: error: {exc}\n")
    network = canopen.Network(bus)
    network.connect()
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(0))
    try:
        network.add_node(canopen.LocalNode(args.node, sdo_dictionary()))
        print("ready", flush=True)
        sys.stdin.read()  # until the bench closes our input (or terminates us)
    finally:
        network.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main())
