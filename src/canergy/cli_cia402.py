"""``canergy supervisor --cia402 IDS``: flags and set-up of guarded CiA 402 drives."""

from __future__ import annotations

import argparse
import math
import secrets
from fractions import Fraction
from pathlib import Path
from typing import Any

import can

from canergy.cia402.guard import DriveGuard, GuardConfig
from canergy.cia402.meter import MeterConfig, MeterKind
from canergy.cli_args import add_duration, bounded_int, duration, energy, node_ids
from canergy.codec import Codec
from canergy.core import Timing
from canergy.live.cia402_host import GuardedSupervisor, HostBeat
from canergy.live.cia402_link import EDS, DriveLink, LinkConfig
from canergy.live.service import SupervisorService

CONSUMER_MAX_US = 65_535_000  # 0x1016 holds milliseconds in 16 bits


def _number(what: str, high: float, *, zero: bool) -> Any:
    """A decimal number of ``what`` (exact, as a fraction), up to ``high``; 0 only if ``zero``."""

    def parse(text: str) -> Fraction:
        try:
            value = Fraction(text.strip())
        except (ValueError, ZeroDivisionError):
            raise argparse.ArgumentTypeError(f"not a number of {what}: {text[:40]!r}") from None
        low = "0" if zero else "more than 0"
        if value > high or value < 0 or (value == 0 and not zero):
            raise argparse.ArgumentTypeError(
                f"{text[:40]}: must be {low} and at most {high} {what}"
            )
        return value

    return parse


def add_cia402_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "CiA 402 drives",
        "guard off-the-shelf CANopen drives: each gets a proxy client in the supervisor's books, "
        "is metered from its TPDOs, and is quick-stopped and disabled when its budget runs out "
        "or its TPDOs stop; the drives consume the host's heartbeat (0x1016) and fault when it "
        "stops",
    )
    g.add_argument("--cia402", type=node_ids, metavar="IDS", help="drive node ids, e.g. 10-12")
    g.add_argument("--cia402-eds", type=Path, help=f"the drives' EDS (default: {EDS.name})")
    g.add_argument(
        "--cia402-meter",
        choices=[k.value for k in MeterKind],
        default=MeterKind.MECHANICAL.value,
        help="mechanical: 0x6077 × 0x6076 × 0x606C (+ R·i² from 0x6078); electrical: 0x6079 × "
        "--cia402-bus-current (default mechanical)",
    )
    g.add_argument(
        "--cia402-bus-current",
        type=bounded_int(0x2000, 0x5FFF),
        metavar="INDEX",
        help="electrical metering: the object holding the DC link current in mA, e.g. 0x2010",
    )
    g.add_argument(
        "--cia402-resistance",
        type=_number("ohms", 1000, zero=True),
        default=Fraction(0),
        metavar="OHMS",
        help="mechanical metering: winding resistance (hot), for copper losses (default 0)",
    )
    g.add_argument(
        "--cia402-velocity-unit",
        type=_number("rad/s", 1000, zero=False),
        default=Fraction(1, 1000),
        metavar="RAD_S",
        help="what one unit of 0x606C is in rad/s (default 0.001; rpm: 0.10471975512)",
    )
    g.add_argument(
        "--cia402-credit-regen",
        action="store_true",
        help="let power flowing back offset energy drawn later (default: not credited)",
    )
    g.add_argument(
        "--cia402-reserve",
        type=energy,
        default=0,
        help="quick stop when a drive's budget falls to this; at least the overshoot bound "
        "keeps it inside what was granted (default 0)",
    )
    g.add_argument(
        "--cia402-enable",
        action="store_true",
        help="bring a drive to OPERATION ENABLED while it holds budget (default: the "
        "application enables it; the guard only stops it)",
    )
    add_duration(g, "--cia402-pdo-timeout", 200_000, "quick stop when TPDOs stop this long")
    add_duration(g, "--cia402-stop-timeout", 1_000_000, "disable this long after quick stop")
    add_duration(g, "--cia402-heartbeat", 100_000, "host heartbeat period")
    add_duration(
        g,
        "--cia402-consumer-timeout",
        500_000,
        "written to each drive's 0x1016:1: it faults after this long without the host",
    )
    g.add_argument("--cia402-sync", type=duration, metavar="TIME", help="send SYNC this often")
    g.add_argument("--cia402-host-id", type=bounded_int(1, 127), default=127)
    g.add_argument(
        "--cia402-capture",
        type=Path,
        metavar="FILE",
        help="log the proxies' canergy frames (any python-can format: .log, .asc, .blf, .csv) "
        "for `canergy audit`",
    )


def check_cia402(args: argparse.Namespace) -> None:
    """Everything about the drives that can be judged before the bus is opened."""
    drives = args.cia402 or ()
    nodes = args.nodes or ()
    if not drives and not nodes:
        raise ValueError("give --nodes, --cia402 or both (or --bus for several buses)")
    if not drives:
        return
    if set(drives) & set(nodes):
        raise ValueError("a node id is either a canergy node (--nodes) or a drive (--cia402)")
    if args.cia402_host_id in (*drives, *nodes):
        raise ValueError(f"--cia402-host-id {args.cia402_host_id} is also a node or drive id")
    if args.cia402_meter == MeterKind.ELECTRICAL.value and args.cia402_bus_current is None:
        raise ValueError("--cia402-meter electrical needs --cia402-bus-current INDEX")
    if args.cia402_consumer_timeout > CONSUMER_MAX_US or args.cia402_consumer_timeout % 1000:
        raise ValueError("--cia402-consumer-timeout: whole milliseconds, at most 65535ms")
    if args.cia402_consumer_timeout < 2 * args.cia402_heartbeat:
        raise ValueError(
            "--cia402-consumer-timeout must be at least twice --cia402-heartbeat, or one late "
            "heartbeat faults the drives"
        )
    if args.listen_only:
        raise ValueError("--cia402 guards drives and must send: not with --listen-only")
    import canopen

    try:
        canopen.import_od(str(args.cia402_eds or EDS))
    except Exception as exc:  # canopen raises what its parsers raise
        raise ValueError(f"--cia402-eds {args.cia402_eds}: not a usable EDS ({exc})") from None


def guard_drives(
    args: argparse.Namespace,
    network: Any,
    bus: can.BusABC,
    service: SupervisorService,
    timing: Timing,
    now: int,
    clock: Any,
) -> GuardedSupervisor:
    meter = MeterConfig(
        kind=MeterKind(args.cia402_meter),
        velocity_unit_rad_s=args.cia402_velocity_unit,
        resistance_mohm=math.ceil(args.cia402_resistance * 1000),
        bus_current_index=args.cia402_bus_current,
        credit_regen=args.cia402_credit_regen,
    )
    config = GuardConfig(
        meter=meter,
        timing=timing,
        pdo_timeout_us=args.cia402_pdo_timeout,
        stop_timeout_us=args.cia402_stop_timeout,
        reserve_uj=args.cia402_reserve,
        auto_enable=args.cia402_enable,
    )
    link_config = LinkConfig(
        eds=args.cia402_eds or EDS,
        meter=meter,
        host_id=args.cia402_host_id,
        consumer_timeout_ms=args.cia402_consumer_timeout // 1000,
    )
    # the capture first: a file that cannot be opened leaves no link thread behind
    capture = can.Logger(str(args.cia402_capture)) if args.cia402_capture else None
    drives = {
        n: (
            DriveGuard(n, config, now, secrets.randbits(16)),
            DriveLink(network, n, link_config, clock),
        )
        for n in args.cia402
    }
    beat = HostBeat(args.cia402_host_id, args.cia402_heartbeat, args.cia402_sync)
    codec = Codec(args.id_base)
    return GuardedSupervisor(service, drives, bus, beat, now, codec=codec, capture=capture)
